"""Show what the model gets wrong (residual strata, growth law, overlays) and write the
discovery report: ``report.md``, ``report.json`` (DESIGN §5.3) and PNG plots.

The residual of tracked points ``r_p(t) = x_obs - x_sim`` is decomposed (reference
algorithms §6.3):

* **phase** of each observed frame, from the observed points' distance to the colliders:
  *free flight* (no point within ``1.5 dx`` of a collider), *impact* (the first frames of a
  contact, or the contact band filling up), *post-contact*, *settling* (mean speed below
  10 % of its maximum after contact);
* **region** of each point: the contact band of each collider, the free surface (fewer
  neighbours than 75 % of the median count within 1.6 particle spacings), the interior;
* **direction**: normal / tangential to the nearest collider (contact band), and vertical
  (along gravity) / horizontal (all points);
* **rigid part**: centre-of-mass residual, rigid rotation residual, shape residual;
* **growth law**: the log-log slope of the centre-of-mass residual against time over the
  free-flight frames (2: an acceleration error; 1: a velocity error; 0: an offset).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from . import extensions as X
from .fit_report import aligned, numerics_cells, numerics_columns
from .numerics import NUMERICS_NOTE_STDS, NUMERICS_REFIT_STEPS, transfer_name

PHASES = ("free flight", "impact", "post-contact", "settling")


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


# =========================================================================== predictions


def predictions(discovery, theta):
    """Per sequence: simulated tracks / probe values / silhouettes at the observed times.

    Returns a list (one per sequence) of dicts with ``"x"`` ``(T, N, D)`` at the observed
    times (tracks), ``"probes"`` ``(P, Tp)``, ``"alpha"`` ``(V, T, n)`` and the residual
    vector ``"r"`` of that sequence.
    """
    from .identify.residuals import Probes, Silhouette, hermite

    problem = discovery.problem
    trajs = problem.trajectories(theta)
    r_all = problem.residuals(theta, trajectories=trajs)
    out, start = [], 0
    for sd, (frames, ok, p) in zip(problem.seqs, trajs):
        x, v = frames.x, frames.v
        t0 = problem._t0(p)
        item = {"ok": ok, "frames_x": np.asarray(x), "params": p}
        obs = sd.seq.observation
        if obs.positions is not None:
            item["x"] = np.asarray(hermite(x, v, jnp.asarray(obs.times, x.dtype), t0, sd.model.frame_dt))
        for o in sd.observables:
            if isinstance(o, Probes):
                P, Pdot = o.frame_values(frames)
                vals = [np.asarray(hermite(P[:, i], Pdot[:, i], o.times[i], t0, o.frame_dt)) for i in range(len(o.fns))]
                item["probes"] = np.stack(vals)
            if isinstance(o, Silhouette):
                item["silhouette"] = o
                item["x_sil"] = np.asarray(hermite(x, v, o.times, t0, o.frame_dt))
        n = int(sum(sd.sizes))
        item["r"] = r_all[start:start + n]
        start += n
        out.append(item)
    return out


# =========================================================================== decomposition


def _contact(model, xs, times, band):
    """Per frame and point: the nearest collider (-1: none within ``band``), its distance and normal."""
    T, N, D = xs.shape
    near = np.full((T, N), -1)
    dist = np.full((T, N), np.inf)
    normal = np.zeros((T, N, D))
    for k, c in enumerate(model.colliders):
        for t in range(T):
            try:
                sd, n = c.signed_distance(jnp.asarray(xs[t], jnp.float32), jnp.asarray(times[t], jnp.float32))
            except Exception:  # noqa: BLE001 - a collider without an analytic distance: skip it
                break
            sd, n = np.abs(np.asarray(sd, float)), np.asarray(n, float)
            closer = (sd < dist[t]) & (sd < band)
            near[t] = np.where(closer, k, near[t])
            dist[t] = np.where(closer, sd, dist[t])
            normal[t] = np.where(closer[:, None], n, normal[t])
    return near, dist, normal


def _free_surface(x, spacing):
    from scipy.spatial import cKDTree

    tree = cKDTree(x)
    counts = np.array([len(c) for c in tree.query_ball_point(x, 1.6 * spacing)])
    return counts < 0.75 * np.median(counts)


def _phases(times, in_contact_frac, speed):
    T = len(times)
    phase = np.array(["free flight"] * T, dtype=object)
    touching = in_contact_frac > 0
    if touching.any():
        first = int(np.argmax(touching))
        vmax = max(float(np.max(speed)), 1e-12)
        for t in range(first, T):
            rising = t > 0 and in_contact_frac[t] > in_contact_frac[t - 1] + 0.05
            if t - first < max(1, T // 10) or rising:
                phase[t] = "impact"
            elif speed[t] < 0.1 * vmax:
                phase[t] = "settling"
            else:
                phase[t] = "post-contact" if touching[t] else "free flight"
    return phase


def decompose_tracks(model, obs, x_sim, gravity, valid_frames=None) -> dict:
    """The residual strata of tracked points (see the module docstring).

    Arguments:
        model: the base model (colliders, grid).
        obs: the observation (``positions`` with ``point_ids = "particles"``).
        x_sim: simulated positions at the observed times, ``(T, N, D)``.
        gravity: the gravity vector (its direction is "vertical").
    """
    x_obs = np.asarray(obs.positions, float)
    times = np.asarray(obs.times, float)
    T, N, D = x_obs.shape
    valid = ~np.any(np.isnan(x_obs), axis=-1)
    xo = np.where(valid[..., None], x_obs, x_sim)
    r = np.where(valid[..., None], xo - x_sim, 0.0)
    dx = model.grid.dx
    spacing = float(np.max(np.concatenate([np.asarray(b.vol0) for b in model.bodies]))) ** (1.0 / D)
    near, _, normal = _contact(model, xo, times, 1.5 * dx)
    up = -np.asarray(gravity, float)
    up = up / max(np.linalg.norm(up), 1e-12)
    # rigid decomposition
    com = np.sum(r * valid[..., None], axis=1) / np.maximum(valid.sum(1), 1)[:, None]
    xbar = np.sum(x_sim * valid[..., None], axis=1) / np.maximum(valid.sum(1), 1)[:, None]
    rot = np.zeros_like(r)
    for t in range(T):
        q = x_sim[t] - xbar[t]
        rr = r[t] - com[t]
        if D == 2:
            perp = np.stack([-q[:, 1], q[:, 0]], -1)
            den = np.sum(valid[t] * np.sum(perp * perp, -1))
            w = np.sum(valid[t] * np.sum(rr * perp, -1)) / max(den, 1e-300)
            rot[t] = w * perp
        else:
            A = np.zeros((3, 3))
            b = np.zeros(3)
            for i in np.flatnonzero(valid[t]):
                K = np.array([[0, q[i, 2], -q[i, 1]], [-q[i, 2], 0, q[i, 0]], [q[i, 1], -q[i, 0], 0]])  # w x q = K w
                A += K.T @ K
                b += K.T @ rr[i]
            w = np.linalg.lstsq(A, b, rcond=None)[0]
            rot[t] = np.cross(np.broadcast_to(w, q.shape), q)
    shape = r - com[:, None, :] - rot
    # regions
    region = np.full((T, N), "interior", dtype=object)
    for t in range(T):
        fs = _free_surface(xo[t], spacing)
        region[t][fs] = "free surface"
        for k, c in enumerate(model.colliders):
            region[t][near[t] == k] = f"contact: {c.name}"
    # phases
    frac = np.array([np.mean(near[t][valid[t]] >= 0) if valid[t].any() else 0.0 for t in range(T)])
    vel = np.gradient(xo, times, axis=0) if T > 1 else np.zeros_like(xo)
    speed = np.sqrt(np.mean(np.sum(vel**2, -1), axis=1))
    phase = _phases(times, frac, speed)

    def ms(a, sel=None):
        sq = np.sum(a * a, -1)
        sel = valid if sel is None else (valid & sel)
        return float(np.sum(sq[sel]) / max(valid.sum(), 1))  # share of the total mean square

    total = ms(r)
    rows = {"rigid part": {}, "phase": {}, "region": {}, "direction": {}}
    rows["rigid part"] = {"centre of mass": ms(np.broadcast_to(com[:, None], r.shape)), "rotation": ms(rot), "shape": ms(shape)}
    for ph in PHASES:
        sel = np.broadcast_to((phase == ph)[:, None], (T, N))
        if sel.any():
            rows["phase"][ph] = ms(r, sel)
    for reg in sorted(set(region.ravel())):
        rows["region"][reg] = ms(r, region == reg)
    vert = np.sum(r * up, -1)
    horiz = r - vert[..., None] * up
    rows["direction"]["vertical"] = ms(vert[..., None])
    rows["direction"]["horizontal"] = ms(horiz)
    incontact = near >= 0
    if incontact.any():
        rn = np.sum(r * normal, -1)
        rt = r - rn[..., None] * normal
        rows["direction"]["contact normal"] = ms(np.where(incontact, rn, 0.0)[..., None])
        rows["direction"]["contact tangential"] = ms(np.where(incontact[..., None], rt, 0.0))
    # per-frame series
    def series(a, sel=None):
        sq = np.sum(a * a, -1)
        m = valid if sel is None else (valid & sel)
        return np.sqrt(np.sum(np.where(m, sq, 0.0), 1) / np.maximum(m.sum(1), 1))

    per_frame = {
        "total": series(r),
        "centre of mass": np.linalg.norm(com, axis=-1),
        "shape": series(shape),
        "vertical": series(vert[..., None]),
        "horizontal": series(horiz),
    }
    if incontact.any():
        per_frame["contact normal"] = series(np.where(incontact, np.sum(r * normal, -1), 0.0)[..., None], incontact)
        rt = r - np.sum(r * normal, -1)[..., None] * normal
        per_frame["contact tangential"] = series(np.where(incontact[..., None], rt, 0.0), incontact)
    per_region = {reg: series(r, region == reg) for reg in sorted(set(region.ravel()))}
    # growth law of the COM residual
    g = np.linalg.norm(com, axis=-1)
    ff = (phase == "free flight") & (times > 0) & (g > 1e-12)
    use = ff if ff.sum() >= 3 else (times > 0) & (g > 1e-12)
    slope = None
    if use.sum() >= 3:
        slope = float(np.polyfit(np.log(times[use]), np.log(g[use]), 1)[0])
    return {
        "total_ms": total,
        "strata": rows,
        "per_frame": per_frame,
        "per_region": per_region,
        "phase": phase.tolist(),
        "times": times,
        "growth_slope": slope,
        "growth_frames": "free flight" if ff.sum() >= 3 else "all",
        "com": com,
    }


def signature_hints(strata: dict, convergence: dict) -> list[str]:
    """Plain-language reading of the residual strata against the signature table (§6.3)."""
    hints = []
    tot = max(strata["total_ms"], 1e-300)
    rp = strata["strata"]["rigid part"]
    com_share = rp.get("centre of mass", 0.0) / tot
    slope = strata["growth_slope"]
    if com_share > 0.6:
        hints.append(f"{com_share:.0%} of the error is a rigid shift of the centre of mass (the body as a whole is in the wrong place).")
        if slope is not None:
            if slope > 1.5:
                hints.append(f"It grows like t^{slope:.1f} ({strata['growth_frames']} frames): an acceleration is wrong "
                             "(gravity, drag, friction, a pushing collider).")
            elif slope > 0.5:
                hints.append(f"It grows like t^{slope:.1f}: a velocity is wrong (initial velocity, a moving collider).")
            else:
                hints.append(f"It grows like t^{slope:.1f}: an offset (time offset, initial position, camera).")
    elif rp.get("shape", 0.0) / tot > 0.5:
        hints.append(f"{rp['shape'] / tot:.0%} of the error is in the shape (deformation), not the rigid motion: "
                     "material parameters, heterogeneity, rate dependence or damping.")
    reg = strata["strata"]["region"]
    contact = {k: v for k, v in reg.items() if k.startswith("contact")}
    if contact:
        k, v = max(contact.items(), key=lambda kv: kv[1])
        if v / tot > 0.4:
            d = strata["strata"]["direction"]
            tang, norm = d.get("contact tangential", 0.0), d.get("contact normal", 0.0)
            kind = "tangential (sliding: friction)" if tang > norm else "normal (bounce / penetration: restitution, collider placement)"
            hints.append(f"{v / tot:.0%} of the error sits in the {k.split(': ')[1]!r} contact band, mostly {kind}.")
    ph = strata["strata"]["phase"]
    if ph:
        k, v = max(ph.items(), key=lambda kv: kv[1])
        hints.append(f"The largest share by phase is {k} ({v / tot:.0%}).")
    if convergence and convergence.get("numerical_fraction", 0.0) > 0.3:
        hints.append(f"Refining dt moves the prediction by {convergence['numerical_fraction']:.0%} of the error: "
                     "part of the residual is numerical.")
    if convergence and (convergence.get("transfer_fraction") or 0.0) > 0.3 and not convergence["data_made_by_model"]:
        hints.append(f"The other transfer moves the prediction by {convergence['transfer_fraction']:.0%} of the error: "
                     "part of the residual may be the grid's numerical dissipation.")
    return hints


# =========================================================================== plots


def _shade_heldout(ax, times, heldout):
    if heldout is not None and np.any(heldout):
        t = np.asarray(times)[np.asarray(heldout)]
        ax.axvspan(float(np.min(t)), float(np.max(t)), color="0.9", zorder=0, label="held out")


def plot_errors(path, discovery, base_pred, ext_pred):
    """Per-group RMS error over time, base vs extended, held-out groups shaded."""
    plt = _pyplot()
    problem = discovery.problem
    g = problem.groups
    mse_b = problem.group_mse(np.concatenate([p["r"] for p in base_pred]))
    mse_e = problem.group_mse(np.concatenate([p["r"] for p in ext_pred]))
    keys = sorted({(int(s), k) for s, k in zip(g.sequence, g.kind)})
    fig, axes = plt.subplots(len(keys), 1, figsize=(6.4, 2.6 * len(keys)), dpi=110, squeeze=False)
    for ax, (s, k) in zip(axes[:, 0], keys):
        sel = (g.sequence == s) & (np.asarray(g.kind) == k)
        t = g.time[sel]
        o = np.argsort(t)
        _shade_heldout(ax, t, discovery.heldout_groups[sel])
        ax.plot(t[o], np.sqrt(mse_b[sel][o]), "o-", ms=3, color="C3", label="base model")
        if discovery.discrepancy:
            ax.plot(t[o], np.sqrt(mse_e[sel][o]), "s-", ms=3, color="C0", label="extended: " + " + ".join(discovery.causes))
        ax.set_ylabel("RMS error")
        ax.set_title(f"{problem.seqs[s].seq.name}: {k}", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    axes[-1, 0].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_strata(path, strata, heldout_times=None):
    plt = _pyplot()
    t = strata["times"]
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4), dpi=110)
    ax = axes[0]
    colors = {"free flight": "C0", "impact": "C3", "post-contact": "C2", "settling": "C7"}
    total = strata["per_frame"]["total"]
    for ph in PHASES:
        sel = np.asarray(strata["phase"]) == ph
        if sel.any():
            ax.bar(t[sel], total[sel], width=0.8 * (t[1] - t[0] if len(t) > 1 else 1.0), color=colors[ph], label=ph)
    ax.set_title("by time phase")
    ax.set_ylabel("RMS residual (m)")
    ax = axes[1]
    for name, s in strata["per_region"].items():
        ax.plot(t, s, "o-", ms=3, label=name)
    ax.set_title("by region")
    ax = axes[2]
    for name in ("centre of mass", "shape", "vertical", "horizontal", "contact normal", "contact tangential"):
        if name in strata["per_frame"]:
            ax.plot(t, strata["per_frame"][name], "o-", ms=3, label=name)
    ax.set_title("by component / direction")
    for ax in axes:
        ax.set_xlabel("time (s)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        if heldout_times is not None and len(heldout_times):
            ax.axvline(float(np.min(heldout_times)), color="k", ls=":", lw=1)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_growth(path, strata):
    plt = _pyplot()
    t, g = strata["times"], np.linalg.norm(strata["com"], axis=-1)
    ok = (t > 0) & (g > 0)
    fig, ax = plt.subplots(figsize=(4.6, 3.4), dpi=110)
    if ok.any():
        ax.loglog(t[ok], g[ok], "o-", ms=3, label="|centre-of-mass residual|")
        t0, g0 = t[ok][0], g[ok][0]
        for p, ls in ((1, "--"), (2, ":")):
            ax.loglog(t[ok], g0 * (t[ok] / t0) ** p, "k" + ls, lw=0.8, label=f"slope {p}")
    s = strata["growth_slope"]
    ax.set_title("growth law" + ("" if s is None else f": slope {s:.2f}"))
    ax.set_xlabel("time (s)")
    ax.set_ylabel("m")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_track_overlay(path, obs, x_base, x_ext, title, heldout_frames, causes):
    plt = _pyplot()
    x_obs = np.asarray(obs.positions, float)
    T = len(x_obs)
    picks = sorted(set(np.linspace(0, T - 1, 4).round().astype(int).tolist()))
    fig, axes = plt.subplots(1, len(picks), figsize=(3.2 * len(picks), 3.2), dpi=110, squeeze=False)
    lo = np.nanmin(np.concatenate([x_obs, x_base]).reshape(-1, x_obs.shape[-1]), axis=0)
    hi = np.nanmax(np.concatenate([x_obs, x_base]).reshape(-1, x_obs.shape[-1]), axis=0)
    pad = 0.05 * np.max(hi - lo)
    for ax, t in zip(axes[0], picks):
        ax.scatter(x_obs[t, :, 0], x_obs[t, :, 1], s=6, c="k", label="observed")
        ax.scatter(x_base[t, :, 0], x_base[t, :, 1], s=6, facecolors="none", edgecolors="C3", label="base model")
        if x_ext is not None:
            ax.scatter(x_ext[t, :, 0], x_ext[t, :, 1], s=4, c="C0", marker="x", lw=0.6, label="extended")
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        ax.set_aspect("equal")
        ax.set_title(f"t = {obs.times[t]:.3g} s" + (" (held out)" if heldout_frames is not None and heldout_frames[t] else ""),
                     fontsize=8)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(title + ("" if x_ext is None else f" — extended with {' + '.join(causes)}"), fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_probes(path, obs, base_vals, ext_vals, causes, heldout_time=None):
    plt = _pyplot()
    names = list(obs.probe_names)
    fig, axes = plt.subplots(len(names), 1, figsize=(6.4, 2.8 * len(names)), dpi=110, squeeze=False)
    for i, (ax, n) in enumerate(zip(axes[:, 0], names)):
        t = np.asarray(obs.probe_times[i], float)
        ok = np.isfinite(t) & np.isfinite(np.asarray(obs.probe_values[i], float))
        o = np.argsort(t[ok])
        ax.plot(t[ok][o], np.asarray(obs.probe_values[i])[ok][o], "ko", ms=3, label="measured")
        ax.plot(t[ok][o], base_vals[i][ok][o], "-", color="C3", label="base model")
        if ext_vals is not None:
            ax.plot(t[ok][o], ext_vals[i][ok][o], "-", color="C0", label="extended: " + " + ".join(causes))
        if heldout_time is not None:
            ax.axvline(heldout_time, color="k", ls=":", lw=1)
        ax.set_ylabel(n)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    axes[-1, 0].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_silhouettes(path, obs, sil, x_base, x_ext):
    """Observed masks and rendered silhouettes (view 0) at a few frames."""
    from .render import render_pixels

    plt = _pyplot()
    masks = np.asarray(obs.masks)
    V, T, H, W = masks.shape
    picks = sorted(set(np.linspace(0, T - 1, 4).round().astype(int).tolist()))
    rows = 2 if x_ext is None else 3
    fig, axes = plt.subplots(rows, len(picks), figsize=(2.4 * len(picks), 2.4 * rows), dpi=110, squeeze=False)
    allpix = jnp.broadcast_to(jnp.arange(H * W, dtype=jnp.int32), (V, H * W))
    for j, t in enumerate(picks):
        axes[0, j].imshow(masks[0, t], cmap="gray")
        axes[0, j].set_title(f"observed t={obs.times[t]:.3g}s", fontsize=7)
        for i, xs in ((1, x_base), (2, x_ext)):
            if xs is None:
                continue
            a = render_pixels(sil.renderer, sil.lifted(jnp.asarray(xs[t])), sil.cameras, allpix, silhouette_only=True)
            axes[i, j].imshow(np.asarray(a[0]).reshape(H, W), cmap="gray", vmin=0, vmax=1)
            axes[i, j].contour(masks[0, t] > 127, levels=[0.5], colors="r", linewidths=0.6)
            axes[i, j].set_title(("base" if i == 1 else "extended") + " (red: observed)", fontsize=7)
    for ax in axes.ravel():
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_candidates(path, discovery):
    plt = _pyplot()
    cands = [c for c in discovery.candidates if c.step == 1]
    if not cands:
        return False
    names = [c.id for c in cands][::-1]
    score = [max(c.score, 0.0) for c in cands][::-1]
    gain = [np.nan if c.gain is None else c.gain for c in cands][::-1]
    y = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(6.4, 0.35 * len(names) + 1.2), dpi=110)
    ax.barh(y + 0.2, score, height=0.4, color="C7", label="score (predicted share of training error removed)")
    ax.barh(y - 0.2, np.nan_to_num(gain, nan=0.0), height=0.4, color="C0", label="measured held-out gain (refitted)")
    for yi, c in zip(y, cands[::-1]):
        if c.selected:
            ax.text(1.01, yi, "selected", va="center", fontsize=7, color="C2")
    ax.set_yticks(y)
    ax.set_yticklabels(names, fontsize=8)
    ax.axvline(discovery.settings["min_gain"], color="k", ls=":", lw=1)
    ax.set_xlim(min(0.0, np.nanmin(np.asarray(gain, float)) if np.isfinite(np.asarray(gain, float)).any() else 0.0), 1.15)
    ax.set_xlabel("fraction")
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return True


# =========================================================================== report


def _fmt(v, digits=4) -> str:
    if v is None:
        return "-"
    a = np.asarray(v, float)
    if a.ndim:
        return "[" + ", ".join(f"{x:.{digits}g}" for x in a.ravel()) + "]"
    return f"{float(a):.{digits}g}"


def _pm(v, s) -> str:
    a, b = np.asarray(v, float), np.asarray(s, float) if s is not None else None
    if b is None:
        return _fmt(a)
    if a.ndim:
        return "[" + ", ".join(f"{x:.4g} ± {y:.2g}" for x, y in zip(a.ravel(), np.broadcast_to(b, a.shape).ravel())) + "]"
    return f"{float(a):.4g} ± {float(b):.2g}"


def write_report(discovery, out_dir, *, title: str = "Discrepancy report", data_note: str | None = None) -> dict:
    """Write ``report.md``, ``report.json`` and the plots into ``out_dir``.

    Returns:
        ``{"report.md": path, "report.json": path, "plots": [paths], "strata": [...]}``.
    """
    from .observe import atomic_write

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    problem = discovery.problem
    base_pred = predictions(discovery, discovery.base_theta)
    ext_pred = predictions(discovery, discovery.extended_theta) if discovery.discrepancy else base_pred
    plots = []
    plot_errors(out / "errors_over_time.png", discovery, base_pred, ext_pred)
    plots.append("errors_over_time.png")
    if plot_candidates(out / "candidates.png", discovery):
        plots.append("candidates.png")
    strata_all = []
    heldout = discovery.heldout_groups
    g = problem.groups
    for i, (sd, bp, ep) in enumerate(zip(problem.seqs, base_pred, ext_pred)):
        obs = sd.seq.observation
        tag = f"_{i}" if len(problem.seqs) > 1 else ""
        seq_held = heldout[g.sequence == i]
        if obs.positions is not None and "x" in bp:
            held_frames = None
            kinds = np.asarray(g.kind)[g.sequence == i]
            if np.sum(kinds == "tracks") == len(obs.times):
                held_frames = seq_held[kinds == "tracks"]
            name = f"overlay{tag}.png"
            plot_track_overlay(out / name, obs, bp["x"], ep["x"] if discovery.discrepancy else None, sd.seq.name,
                               held_frames, discovery.causes)
            plots.append(name)
            if obs.point_ids == "particles" and obs.positions.shape[-1] >= 2:
                grav = np.asarray(X.strip(sd.params)["gravity"], float)
                st = decompose_tracks(sd.model, obs, bp["x"], grav)
                st["sequence"] = sd.seq.name
                strata_all.append(st)
                ht = np.asarray(obs.times)[held_frames] if held_frames is not None else None
                plot_strata(out / f"residual_strata{tag}.png", st, ht)
                plot_growth(out / f"growth{tag}.png", st)
                plots += [f"residual_strata{tag}.png", f"growth{tag}.png"]
        if obs.probe_names is not None and "probes" in bp:
            name = f"probes{tag}.png"
            ht = None
            ptimes = g.time[(g.sequence == i)][seq_held]
            if len(ptimes):
                ht = float(np.min(ptimes))
            plot_probes(out / name, obs, bp["probes"], ep["probes"] if discovery.discrepancy else None,
                        discovery.causes, ht)
            plots.append(name)
        if obs.masks is not None and "silhouette" in bp:
            name = f"silhouettes{tag}.png"
            plot_silhouettes(out / name, obs, bp["silhouette"], bp["x_sil"], ep["x_sil"] if discovery.discrepancy else None)
            plots.append(name)
    payload = discovery.to_json()
    payload["details"]["strata"] = [
        {"sequence": s["sequence"], "total_mean_square": s["total_ms"],
         "mean_square": {k: v for k, v in s["strata"].items()}, "growth_slope": s["growth_slope"],
         "growth_frames": s["growth_frames"], "hints": signature_hints(s, discovery.convergence)}
        for s in strata_all
    ]
    payload["details"]["plots"] = plots

    def write_json(tmp):
        Path(tmp).write_text(json.dumps(payload, indent=2, default=_json_default) + "\n")

    atomic_write(out / "report.json", write_json)
    md = _markdown(discovery, strata_all, plots, title, data_note)
    atomic_write(out / "report.md", lambda tmp: Path(tmp).write_text(md))
    return {"report.md": out / "report.md", "report.json": out / "report.json", "plots": [out / p for p in plots],
            "strata": strata_all}


def _timing_rows(timing: dict) -> list[tuple[str, ...]]:
    """The ``timing`` block as rows: a header, one row per phase, the totals."""
    rows = [("phase", "wall s", "rollouts", "s", "Jacobian rollouts (tangents)", "s", "LM runs / iterations / rejected",
             "compile s", "host s")]
    for r in [*timing["phases"], dict(timing["totals"], phase="all", wall_s=timing["total_s"])]:
        rows.append((r["phase"], f"{r['wall_s']:.1f}", str(r["rollouts"]), f"{r['rollout_s']:.1f}",
                     f"{r['jvp_rollouts']} ({r['tangents']})", f"{r['jvp_s']:.1f}",
                     f"{r['fits']} / {r['iterations']} / {r['rejected_steps']}" if r["fits"] else "-",
                     f"{r['compile_s']:.1f}", f"{r['host_s']:.1f}"))
    return rows


def format_timing(discovery) -> str:
    """Where :func:`jaxmpm.discover`'s time went (``discovery.timing``), as a text table."""
    return "\n".join(line.rstrip() for line in aligned(_timing_rows(discovery.timing)))


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o))


def _markdown(d, strata_all, plots, title, data_note) -> str:
    s = d.settings
    L = [f"# {title}", ""]
    L += ["## Verdict", "", f"**{d.verdict}**", ""]
    if d.discrepancy:
        L += ["| | held-out error | training error |", "|---|---|---|",
              f"| base model | {d.base_error:.4g} | {d.base_train_error:.4g} |",
              f"| extended ({' + '.join(d.causes)}) | {d.extended_error:.4g} | {d.extended_train_error:.4g} |",
              f"| **gain** (fraction of held-out error removed) | **{d.gain:.1%}** | |", ""]
        columns = numerics_columns(d.extended_numerics)
        L += ["Fitted extension parameters (± one standard deviation, frame-clustered"
              + ("; the moves: where a short refit of the extended model ends at dt/2 and with the other "
                 "transfer, see \"The base model\" below" if columns else "") + "):", "",
              "| parameter | value |" + "".join(f" {header} |" for _, header in columns), "|---|---|" + "---|" * len(columns)]
        for k, v in d.parameters.items():
            spec = d.problem.entry(k).spec
            unit = spec.unit if spec is not None and spec.unit != "-" else ""
            L.append(f"| `{k}` | {_pm(v, d.std.get(k))} {unit} |"
                     + "".join(f" {c} |" for c in numerics_cells(d.extended_numerics, k)))
        L.append("")
        for e in d.causes:
            L.append(f"* `{e}`: {X.EXTENSIONS[e].title} — acts in the {X.EXTENSIONS[e].acts_in}; "
                     f"typical signature: {X.EXTENSIONS[e].signature}.")
        L.append("")
    else:
        L += [f"Base model held-out error {d.base_error:.4g} (training {d.base_train_error:.4g}).", ""]
    L += ["## Data and protocol", ""]
    if data_note:
        L += [data_note, ""]
    seqs = ", ".join(f"`{n}`" for n in s["sequences"])
    fitted = ", ".join("`" + n + "`" for n in s["names"]) or "none (the base model's parameters are all known)"
    L += [f"* Sequences: {seqs}. Fitted base parameters: {fitted}.",
          f"* Held out: {s['heldout_groups']} of {s['heldout_groups'] + s['train_groups']} frames / time bins "
          + (f"(sequences {', '.join(s['holdout_sequences'])})" if s["holdout_sequences"] else f"(the last {s['holdout']:.0%} of each sequence's observed times: a forecast)")
          + "; every fit uses only the training part.",
          "* Error = RMS over frames of each frame's RMS residual (metres for tracks and probes, opacity for silhouettes). "
          "Points or pixels of one frame share that frame's dynamics error, so a frame (or a frame-length time bin of a "
          "probe) is one sample, not each point.",
          f"* An extension is kept when its held-out gain is at least {s['min_gain']:.0%}, a likelihood-ratio test on the "
          f"training frames (n = {s['train_groups']}; boundary mixture ½χ²₀+½χ²₁ for one bounded parameter) gives p < {s['alpha']}, "
          "and the held-out improvement exceeds the numerical error of the dt/2 check (the transfer check is reported "
          "beside it and is not part of the rule).", ""]
    L += ["## The base model", ""]
    if d.base_values:
        columns = numerics_columns(d.numerics)
        L += ["| parameter | fitted value |" + "".join(f" {header} |" for _, header in columns),
              "|---|---|" + "---|" * len(columns)]
        for k, v in d.base_values.items():
            L.append(f"| `{k}` | {_pm(v, d.base_std.get(k))} |"
                     + "".join(f" {c} |" for c in numerics_cells(d.numerics, k)))
    else:
        L.append("No parameter fitted: the base model is run as given.")
    if d.numerics or d.extended_numerics:
        where = {(True, True): " (here and in the verdict's table)", (False, True): " (in the verdict's table)"}
        L += ["", f"The moves{where.get((bool(d.numerics), bool(d.extended_numerics)), '')} are where a short refit of "
              f"the fitted model (at most {NUMERICS_REFIT_STEPS} iterations) ends at dt/2 and with the other transfer, "
              "less the fitted value: the parameters' numerical error, which the standard deviation does not include "
              "(docs/fitting.md, \"Numerical error of the parameters\"; report.json: `details.numerics`, "
              f"`details.extended_numerics`). A note names a parameter moved by more than {NUMERICS_NOTE_STDS:g} "
              "standard deviations, unless the data may have been made by this model on its grid."]
    if d.notes:
        L += [""] + [f"* Note: {note}" for note in d.notes]
    L.append("")
    L += ["## What the base model gets wrong", ""]
    if "errors_over_time.png" in plots:
        L += ["![error over time](errors_over_time.png)", ""]
    for st in strata_all:
        tot = max(st["total_ms"], 1e-300)
        L += [f"### Residual strata ({st['sequence']})", "",
              f"Share of the mean squared track residual of the fitted base model (total RMS {math.sqrt(st['total_ms']):.3g} m):", "",
              "| stratum | share |", "|---|---|"]
        for group, vals in st["strata"].items():
            for k, v in vals.items():
                L.append(f"| {group}: {k} | {v / tot:.0%} |")
        L.append("")
        if st["growth_slope"] is not None:
            L.append(f"Growth law: the centre-of-mass residual grows like t^{st['growth_slope']:.2f} "
                     f"(log-log slope over {st['growth_frames']} frames).")
            L.append("")
        for h in signature_hints(st, d.convergence):
            L.append(f"* {h}")
        L.append("")
    for p in plots:
        if p.startswith(("residual_strata", "growth", "overlay", "probes", "silhouettes")):
            L += [f"![{p}]({p})", ""]
    L += ["## Convergence check (numerical error vs missing physics)", ""]
    c = d.convergence
    if c:
        L += [f"The fitted base model rerun at dt/2 moves the held-out prediction by {c['numerical_error']:.3g} "
              f"({c['numerical_fraction']:.0%} of the base model's held-out error {c['heldout_error_dt']:.3g}; "
              f"held-out error at dt/2: {c['heldout_error_dt2']:.3g}). "
              + ("Most of the residual is therefore **not** a time-step error." if c["numerical_fraction"] < 0.5 else
                 "The prediction is not converged in dt: it moves by as much as half the residual, so no physical "
                 "explanation smaller than that can be told from the discretisation. Refine dt/dx before trusting one."),
              ""]
        if c.get("transfer_error") is not None:
            at = ("; both at dt/2, since with the other transfer the run is unhealthy at dt"
                  if c.get("transfer_dt_factor", 1.0) != 1.0 else "")
            L += [f"The same model with {transfer_name(c['flip_checked'])} in place of {transfer_name(c['flip'])} in its "
                  f"transfers (docs/materials.md{at}) moves the held-out prediction by {c['transfer_error']:.3g} "
                  f"({c['transfer_fraction']:.0%} of the base model's held-out error; held-out error with it: "
                  f"{c['heldout_error_transfer']:.3g}). The transfers' numerical dissipation is a spatial error that "
                  "refining dt does not reduce. This change is not part of the selection rule, since data made by "
                  "this model on this grid would show it too without being in error; "
                  + ("these data may be this model's own (tracks of its own particles, or made by an embedded "
                     "scene with its dx and transfers), so the verdict says nothing of it."
                     if c.get("data_made_by_model") else
                     "the verdict cautions against an extension whose held-out improvement is within it."), ""]
        elif "transfer_error" in c:
            L += [f"With {transfer_name(c['flip_checked'])} in place of {transfer_name(c['flip'])} the run is unhealthy "
                  "at dt and at dt/2: no transfer check.", ""]
    else:
        L += ["Not run.", ""]
    L += ["## Candidates", "",
          "Score: Gauss–Newton prediction, at the extension's null value, of the share of the training error the extension "
          "removes (base parameters re-adjusted, bounds respected). Gain: measured on held-out data after refitting.", "",
          "| step | extension | score | score p | refit held-out error | gain | LRT | p | parameters | decision |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for cand in d.candidates:
        pars = "; ".join(f"`{k}` = {_pm(v, cand.std.get(k))}" for k, v in cand.parameters.items()) or "-"
        gain = "-" if cand.gain is None else f"{cand.gain:.1%}"
        he = "-" if cand.heldout_error is None else f"{cand.heldout_error:.4g}"
        lrt = "-" if cand.lrt is None else f"{cand.lrt:.3g}"
        pv = "-" if cand.p_value is None else f"{cand.p_value:.2g}"
        L.append(f"| {cand.step} | `{cand.id}` | {cand.score:.3f} | {cand.score_p:.2g} | {he} | {gain} | {lrt} | {pv} | {pars} | {cand.reason} |")
    L.append("")
    if "candidates.png" in plots:
        L += ["![candidates](candidates.png)", ""]
    if d.not_applicable:
        L += ["Not applicable to this scene: " + "; ".join(f"`{k}` ({v})" for k, v in d.not_applicable.items()) + ".", ""]
    if d.timing:
        rows = _timing_rows(d.timing)
        L += ["## Where the time went", "",
              "Seconds per phase; a Jacobian rollout is one primal carrying several tangents; compilation is "
              "estimated as the first calls' excess over later calls of the same program.", "",
              "| " + " | ".join(rows[0]) + " |", "|" + "---|" * len(rows[0])]
        L += ["| " + " | ".join(r) + " |" for r in rows[1:]]
        L.append("")
    L += [f"_jaxmpm discover, {d.seconds:.0f} s._", ""]
    return "\n".join(L)

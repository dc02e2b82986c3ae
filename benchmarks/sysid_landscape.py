"""The track loss of a sysid case along one parameter, against its smooth (Gauss-Newton) part.

A case of ``jaxmpm bench sysid`` (``--case``, a key of ``--preset``) is simulated at its true
parameters; then one log10 parameter (``--name``) is moved by ``--points`` offsets in
``[-span, span]`` decades, and each rollout's positions are compared with the truth's over the
frames up to ``--until`` seconds: the loss is the mean squared distance (m^2) per particle and
frame, the fit's track loss without its normalisation. Beside it, the loss the derivative
predicts, ``mean |J δ|^2`` with ``J`` the forward-mode tangent of the positions at the truth:
what a Levenberg-Marquardt fit sees. For a smooth model the two agree as ``δ → 0``; where the
measured loss is far above the prediction, discrete decisions (CPIC's incompatible nodes, its
reference face, the persistent side tags) make the loss jump, and the jumps, not the
curvature, set how precisely the parameter can be found. ``--float64`` runs both the truth and
the offsets in float64: the same landscape in both precisions means the jumps are the model's,
not round-off.

    python benchmarks/sysid_landscape.py --case newtonian-small-0-tracks-cpic --name mu \\
        --span 0.01 --points 21 --until 0.25 [--smallest 1e-7] [--float64] [--out land.json] [--plot land.png]
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--case", default="newtonian-small-0-tracks-cpic")
    parser.add_argument("--preset", default="reduced", choices=("ci", "reduced", "full"))
    parser.add_argument("--name", default="mu", help="a log10 parameter of the case's material")
    parser.add_argument("--span", type=float, default=0.01, help="largest offset, decades")
    parser.add_argument("--points", type=int, default=21)
    parser.add_argument("--smallest", type=float, default=None,
                        help="log spacing: ±points/2 offsets from this to --span decades (default: linear)")
    parser.add_argument("--until", type=float, default=None, help="last frame time compared, s (default: all)")
    parser.add_argument("--float64", action="store_true")
    parser.add_argument("--out", default=None, help="JSON of the offsets, losses and predictions")
    parser.add_argument("--plot", default=None, help="PNG of loss against |offset| (log-log)")
    args = parser.parse_args(argv)

    import jax

    if args.float64:
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from jaxmpm.bench_sysid import truth_scene
    from jaxmpm.identify.parameters import LOG10_PARAMS, with_values
    from jaxmpm.step import simulate

    dtype = jnp.float64 if args.float64 else jnp.float32
    try:
        scene, case, truth = truth_scene(args.case, args.preset, dtype)
    except ValueError as err:
        parser.error(str(err))
    if args.name not in truth or args.name not in LOG10_PARAMS:
        parser.error(f"--name must be a log10 parameter of {case.material}: {sorted(set(truth) & LOG10_PARAMS)}")
    model = scene.model
    times = np.arange(model.frames) * model.frame_dt
    frames = np.nonzero(times <= (np.inf if args.until is None else args.until + 1e-9))[0]

    def positions(theta):  # log10 of the parameter -> (frames, N, D)
        params = with_values(model, scene.params, {args.name: 10.0 ** theta})
        return simulate(model, params, checkpoint=None).x[frames]

    theta0 = jnp.asarray(np.log10(truth[args.name]), dtype)
    t0 = time.perf_counter()
    x0, dx = jax.jit(lambda t: jax.jvp(positions, (t,), (jnp.ones_like(t),)))(theta0)
    x0, dx = np.asarray(x0, np.float64), np.asarray(dx, np.float64)  # m, m per decade
    run = jax.jit(positions)
    curvature = float(np.mean(np.sum(dx**2, -1)))  # m^2 per decade^2
    print(f"{case.key} ({model.num_particles} particles, {np.dtype(dtype).name}), {args.name} = {truth[args.name]:.6g}, "
          f"frames 0..{frames[-1]} (t <= {times[frames[-1]]:.4g} s); smooth part mean|J|^2 = {curvature:.4e} m^2/decade^2",
          flush=True)
    print(f"{'offset (decades)':>17} {'loss (m^2)':>12} {'J-predicted':>12} {'ratio':>9}")
    if args.smallest is None:
        offsets = np.linspace(-args.span, args.span, args.points)
    else:
        half = np.geomspace(args.smallest, args.span, max(args.points // 2, 1))
        offsets = np.concatenate([-half[::-1], [0.0], half])
    losses, predicted = [], []
    for d in offsets:
        x = np.asarray(run(theta0 + jnp.asarray(d, dtype)), np.float64)
        loss = float(np.mean(np.sum((x - x0) ** 2, -1)))
        pred = curvature * d**2
        losses.append(loss)
        predicted.append(pred)
        ratio = f"{loss / pred:9.3g}" if pred > 0 else f"{'-':>9}"
        print(f"{d:+17.3e} {loss:12.4e} {pred:12.4e} {ratio}", flush=True)
    print(f"({time.perf_counter() - t0:.1f} s)")
    record = {"case": case.key, "preset": args.preset, "dtype": np.dtype(dtype).name, "name": args.name,
              "truth": truth[args.name], "until": args.until, "frames": int(len(frames)),
              "curvature": curvature, "offsets": offsets.tolist(), "loss": losses, "predicted": predicted}
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(record, fh, indent=1)
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5.5, 4))
        nz = offsets != 0
        for sign, marker in ((1, "o"), (-1, "s")):
            sel = nz & (np.sign(offsets) == sign)
            ax.loglog(np.abs(offsets[sel]), np.asarray(losses)[sel], marker, ls="none",
                      label=f"measured, offset {'>' if sign > 0 else '<'} 0")
        grid = np.geomspace(np.abs(offsets[nz]).min(), np.abs(offsets).max(), 50)
        ax.loglog(grid, curvature * grid**2, "k-", label="J-predicted (smooth part)")
        ax.set_xlabel(f"|Δ log10 {args.name}| (decades)")
        ax.set_ylabel("track loss (m²)")
        ax.set_title(f"{case.key}, {np.dtype(dtype).name}", fontsize=9)
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(args.plot, dpi=120)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""``jaxmpm bench sysid``: AS-DiffMPM's identification protocol regenerated with jaxmpm.

AS-DiffMPM (NeurIPS 2025) drops Newtonian, non-Newtonian (viscoplastic) and granular (sand)
material onto Box, Bunny and Armadillo colliders, 16 frames seen by 11 cameras of
PAC-NeRF's rig, and identifies the material parameters from particle tracks or from
images, comparing particle-wise (CPIC) collision handling with grid-level (GOP) and
rigid-particle (RP) baselines. Its sequences and code are not public, so this benchmark
regenerates the protocol: every case simulates a ground truth with jaxmpm (CPIC), observes
it (tracks of every particle; masks and images rendered from the rig), and identifies the
parameters from PAC-NeRF's initial guesses with :func:`jaxmpm.fit` (staged: initial
velocity on the pre-contact frames, then the material on a growing frame window), once per
collision mode. Extra cases: the collider at the side, at 0.5x and 1.5x size, the open
bowl, three colliders, and elastic and plasticine material.

Each identification runs in its own subprocess, so its time (compilation included) and
peak resident memory are its own. Results are appended to ``OUT/results.jsonl`` (a rerun
skips the cases already there) and summarised in ``OUT/table.md``.

Usage::

    jaxmpm bench sysid --preset reduced --out bench_sysid      # what docs/benchmark_sysid.md reports
    jaxmpm bench sysid --preset full --out bench_sysid_full    # the whole protocol (hours to days on a CPU)
    jaxmpm bench sysid --preset ci --out /tmp/ci               # one tiny case
    jaxmpm bench sysid --only newtonian-small --float64 --out bench_sysid_f64   # the same cases in float64
    jaxmpm bench sysid --only silhouettes-cpic --scan none --out bench_sysid_noscan   # without the decade scan
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from .constitutive import MATERIALS as MATERIAL_CLASSES

MATERIALS = ("newtonian", "viscoplastic", "sand", "elastic", "plasticine")
COLLIDERS = ("box", "bunny", "armadillo")
MODES = ("cpic", "grid", "particles")
SUPERVISION = ("tracks", "silhouettes")

#: Fitted parameters per material (AS-DiffMPM: mu, kappa, tau_Y, eta, friction; PAC-NeRF: E, nu).
FIT_NAMES = {
    "newtonian": ["mu", "kappa"],
    "viscoplastic": ["mu", "kappa", "yield_stress", "eta"],
    "sand": ["friction_angle"],
    "elastic": ["E", "nu"],
    "plasticine": ["E", "nu", "yield_stress"],
}

#: PAC-NeRF's initial guesses for its 45-sequence batch (anchors §1.8), as each material declares them.
INITIAL_GUESS = {m: {p.name: p.guess for p in MATERIAL_CLASSES[m].parameters if p.name in FIT_NAMES[m]}
                 for m in MATERIALS}

#: Ranges of the ground-truth parameter sets (log-uniform for log10 parameters), around
#: PAC-NeRF's / GIC's ground truths, limited so that the explicit time step stays stable at
#: the preset's substeps.
TRUTH_RANGES = {
    "newtonian": {"mu": (50.0, 500.0), "kappa": (2e4, 1e5)},
    "viscoplastic": {"mu": (1e3, 5e3), "kappa": (5e4, 2e5), "yield_stress": (200.0, 2e3), "eta": (2.0, 20.0)},
    "sand": {"friction_angle": (25.0, 45.0)},
    "elastic": {"E": (5e4, 5e5), "nu": (0.2, 0.4)},
    "plasticine": {"E": (1e5, 5e5), "nu": (0.2, 0.4), "yield_stress": (2e3, 1e4)},
}
LINEAR = ("nu", "friction_angle")
#: Substeps per frame relative to the preset's, per material (stiffer sand and
#: viscoplastic ground truths need a smaller dt).
SUBSTEP_FACTOR = {"sand": 1.6, "viscoplastic": 1.2, "plasticine": 1.6}
#: Fixed stiffness of sand (PAC-NeRF fixes E = 1e6; a softer sand lets the coarse presets
#: keep dt large: the friction angle alone sets the flow).
SAND_E = 3e5


@dataclass(frozen=True)
class Preset:
    dx: float
    substeps: int
    frames: int
    views: int
    res: int
    pixels: int
    sets: int
    max_steps: int
    cases: tuple = ()


@dataclass(frozen=True)
class Case:
    material: str
    collider: str  # box | bunny | armadillo | side | small | large | bowl | three | none
    index: int  # which ground-truth parameter set
    supervision: str  # tracks | silhouettes
    mode: str  # cpic | grid | particles

    @property
    def key(self) -> str:
        return f"{self.material}-{self.collider}-{self.index}-{self.supervision}-{self.mode}"


def _core(materials, colliders, sets, supervision, modes):
    return [Case(m, c, i, s, mo) for s in supervision for mo in modes for m in materials for c in colliders
            for i in range(sets)]


def preset_cases(name: str) -> tuple[Preset, list[Case]]:
    """The cases and numerical settings of a preset (``ci``, ``reduced``, ``full``)."""
    if name == "ci":
        p = Preset(dx=0.1, substeps=20, frames=6, views=4, res=24, pixels=64, sets=1, max_steps=15)
        return p, [Case("newtonian", "box", 0, "tracks", "cpic")]
    if name == "reduced":
        p = Preset(dx=0.04, substeps=50, frames=16, views=11, res=48, pixels=128, sets=2, max_steps=25)
        core = ("newtonian", "viscoplastic", "sand")
        # ordered so that a partial run still covers every axis of the protocol
        cases = _core(core, COLLIDERS, 1, ["tracks"], ["cpic"])
        cases += _core(core, ["bunny"], 1, ["silhouettes"], ["cpic"])
        cases += _core(core, ["bunny"], 1, ["tracks"], ["grid", "particles"])
        cases += [Case("newtonian", c, 0, "tracks", "cpic") for c in ("side", "small", "large", "bowl", "three")]
        cases += [Case(m, "box", 0, "tracks", "cpic") for m in ("elastic", "plasticine")]
        cases += [Case(m, "bunny", 1, "tracks", "cpic") for m in core]
        cases += [Case(m, c, 0, "silhouettes", "cpic") for m in core for c in ("box", "armadillo")]
        return p, cases
    if name == "full":
        p = Preset(dx=0.02, substeps=100, frames=16, views=11, res=100, pixels=512, sets=5, max_steps=40)
        core = ("newtonian", "viscoplastic", "sand")
        cases = _core(core, COLLIDERS, 5, SUPERVISION, MODES)
        cases += _core(core, ("side", "small", "large", "bowl", "three"), 2, SUPERVISION, ["cpic"])
        cases += _core(("elastic", "plasticine"), COLLIDERS, 2, SUPERVISION, ["cpic"])
        return p, cases
    raise ValueError(f"unknown preset {name!r} (ci, reduced, full)")


def find_case(key: str, preset_name: str = "reduced") -> tuple[Preset, Case]:
    """The preset and the case of key ``key`` (``jaxmpm bench sysid --list``); ValueError if absent."""
    preset, cases = preset_cases(preset_name)
    for case in cases:
        if case.key == key:
            return preset, case
    raise ValueError(f"no case {key!r} in preset {preset_name} (jaxmpm bench sysid --preset {preset_name} --list)")


def truth_scene(key: str, preset_name: str = "reduced", dtype=None):
    """The ground-truth :class:`~jaxmpm.scene.Scene` of case ``key`` (its true parameters, thrown
    at 1 m/s downwards), its case and its true values; for the diagnostics in ``benchmarks/``."""
    from .scene import load_scene

    preset, case = find_case(key, preset_name)
    truth = truth_values(case.material, case.index)
    kwargs = {} if dtype is None else {"dtype": dtype}
    return load_scene(scene_spec(case, preset, truth, TRUE_VELOCITY), **kwargs), case, truth


# --------------------------------------------------------------------------- scenes


def truth_values(material: str, index: int) -> dict:
    """Ground-truth set ``index`` of ``material`` (deterministic, seeded by both)."""
    rng = np.random.default_rng(1000 * MATERIALS.index(material) + index)
    out = {}
    for name, (lo, hi) in TRUTH_RANGES[material].items():
        u = rng.uniform()
        out[name] = float(lo + u * (hi - lo)) if name in LINEAR else float(10 ** (np.log10(lo) + u * np.log10(hi / lo)))
    return out


FLOOR_Y = 0.05


def _colliders(kind: str) -> list[dict]:
    floor = {"type": "plane", "name": "floor", "point": [0.0, FLOOR_Y, 0.0], "normal": [0.0, 1.0, 0.0],
             "contact": "sticky"}

    def mesh(name, path, scale, x=0.5, z=0.5, half_height=None):
        h = 0.5 * scale if half_height is None else half_height
        return {"type": "mesh", "name": name, "path": path, "scale": scale, "translate": [x, FLOOR_Y + h, z],
                "contact": "slip"}

    if kind == "none":
        return [floor]
    if kind == "box":
        return [floor, {"type": "box", "name": "box", "lo": [0.38, FLOOR_Y, 0.38], "hi": [0.62, 0.33, 0.62],
                        "contact": "slip"}]
    if kind == "bunny":
        return [floor, mesh("bunny", "bunny.obj", 0.4, half_height=0.4 * 0.494076)]
    if kind == "armadillo":
        return [floor, mesh("armadillo", "armadillo.obj", 0.4)]
    if kind == "small":
        return [floor, mesh("bunny", "bunny.obj", 0.2, half_height=0.2 * 0.494076)]
    if kind == "large":
        return [floor, mesh("bunny", "bunny.obj", 0.6, half_height=0.6 * 0.494076)]
    if kind == "side":  # the body hits the collider's shoulder, off centre
        return [floor, mesh("bunny", "bunny.obj", 0.4, x=0.62, half_height=0.4 * 0.494076)]
    if kind == "bowl":  # open mesh: rim at y = FLOOR_Y + 0.2, material lands inside
        return [floor, {"type": "mesh", "name": "bowl", "path": "bowl.obj", "scale": 0.5,
                        "translate": [0.5, FLOOR_Y + 0.125, 0.5], "contact": "slip"}]
    if kind == "three":
        return [floor,
                {"type": "box", "name": "box", "lo": [0.25, FLOOR_Y, 0.4], "hi": [0.42, 0.25, 0.6], "contact": "slip"},
                mesh("bunny", "bunny.obj", 0.25, x=0.62, z=0.42, half_height=0.25 * 0.494076),
                mesh("armadillo", "armadillo.obj", 0.25, x=0.6, z=0.65)]
    raise ValueError(f"unknown collider case {kind!r}")


#: Top of each collider case (m), so the body starts above it.
COLLIDER_TOP = {"none": FLOOR_Y, "box": 0.33, "bunny": FLOOR_Y + 0.4 * 0.988152, "armadillo": FLOOR_Y + 0.4,
                "small": FLOOR_Y + 0.2 * 0.988152, "large": FLOOR_Y + 0.6 * 0.988152, "side": FLOOR_Y + 0.4 * 0.988152,
                "bowl": FLOOR_Y + 0.25, "three": FLOOR_Y + 0.25}


def scene_spec(case: Case, preset: Preset, values: dict, velocity=(0.0, -1.0, 0.0)) -> dict:
    """The scene of a case: a 0.2 m cube of material dropped onto the collider(s) from
    0.5 m (or 0.08 m above a taller collider)."""
    material = {"model": case.material, "density": 1000.0, **values}
    y0 = max(0.5, COLLIDER_TOP[case.collider] + 0.08)
    if case.material == "sand":
        material.setdefault("E", SAND_E)
    return {
        "dim": 3,
        "dx": preset.dx,
        "domain": {"lo": [0.0, 0.0, 0.0], "hi": [1.0, 1.0, 1.0]},
        "gravity": [0.0, -9.8, 0.0],
        "frames": preset.frames,
        "frame_dt": 1.0 / 24.0,
        "substeps": int(round(preset.substeps * SUBSTEP_FACTOR.get(case.material, 1.0))),
        "collision": case.mode,
        "bodies": [{"shape": "box", "name": "body", "lo": [0.4, y0, 0.4], "hi": [0.6, y0 + 0.2, 0.6],
                    "ppc": 8, "velocity": list(velocity), "material": material}],
        "colliders": _colliders(case.collider),
    }


def rig(preset: Preset):
    """PAC-NeRF's rig (11 views, 45° field of view, elevations 5°–75°, looking at the
    scene) at a radius that frames the 1 m domain (PAC-NeRF: 3 m for its larger scenes)."""
    from .render import pacnerf_rig

    return pacnerf_rig(preset.views, radius=1.8, target=(0.5, 0.3, 0.5), fov_deg=45.0, res=preset.res)


# --------------------------------------------------------------------------- one case


def errors(names, estimate: dict, truth: dict) -> dict:
    """|Δlog10| for log10 parameters, |Δ| (degrees for the friction angle, raw for ν); ``inf``
    for an estimate outside the log's domain (a fit whose ``10^y`` underflowed to 0)."""
    from .identify.parameters import LOG10_PARAMS

    out = {}
    for n in names:
        e, t = float(np.ravel(estimate[n])[0]), float(truth[n])
        if n in LOG10_PARAMS:
            out[n] = abs(math.log10(e) - math.log10(t)) if e > 0 else math.inf
        else:
            out[n] = abs(e - t)
    return out


def fit_reporters(t0: float) -> dict:
    """``log`` and ``progress`` callbacks for :func:`jaxmpm.fit.fit` that print each message and
    iteration to stderr with the seconds since ``t0`` (a case's log, streamed by the runner)."""

    def say(message):
        print(f"  [{time.perf_counter() - t0:7.1f} s] {message}", file=sys.stderr, flush=True)

    return {"log": say, "progress": lambda i, loss: say(f"iteration {i:3d}  loss {loss:.4e}")}


def code_version() -> str:
    """The commit the package runs from: ``$JAXMPM_COMMIT`` (set it when running from an
    exported snapshot), else ``git rev-parse`` of the package's checkout, else ``"unknown"``."""
    if os.environ.get("JAXMPM_COMMIT"):
        return os.environ["JAXMPM_COMMIT"]
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=Path(__file__).parent,
                             capture_output=True, text=True, timeout=10)
    except OSError:
        return "unknown"
    return out.stdout.strip() if out.returncode == 0 and out.stdout.strip() else "unknown"


TRUE_VELOCITY = (0.0, -1.0, 0.0)  # every case's body is thrown at 1 m/s downwards (m/s)


def observe_case(case: Case, preset: Preset, dtype=None):
    """Simulate ``case`` at its true values (always with CPIC) and observe it as its
    supervision says: every particle's positions (``tracks``) or the rig's rendered masks and
    images (``silhouettes``). Returns ``(observation, truth values, true velocity, ground-truth
    scene)``, or an error message where the ground truth is unstable."""
    from .identify.residuals import make_fit_renderer
    from .observe import Observation
    from .render import render_views
    from .scene import load_scene
    from .step import simulate

    kwargs = {} if dtype is None else {"dtype": dtype}
    truth = truth_values(case.material, case.index)
    gt = load_scene(scene_spec(replace(case, mode="cpic"), preset, truth, TRUE_VELOCITY), **kwargs)
    traj = simulate(gt.model, gt.params, checkpoint=None)
    bad = traj.first_unstable_frame()
    if bad is not None:
        return f"ground truth unstable at frame {bad}"
    x = np.asarray(traj.x)
    obs_kwargs = {"times": np.asarray(traj.times)}
    if case.supervision == "tracks":
        obs_kwargs.update(positions=x, point_ids="particles")
    else:
        rendered = render_views(x, rig(preset), make_fit_renderer("volume", gt.model))
        obs_kwargs.update(masks=rendered["masks"], images=rendered["images"], intrinsics=rendered["intrinsics"],
                          cam_to_world=rendered["cam_to_world"])
    return Observation(**obs_kwargs, scene=gt.to_json()), truth, TRUE_VELOCITY, gt


def start_scene(case: Case, preset: Preset, guess: dict, dtype=None):
    """The scene a fit of ``case`` starts from: the material at ``guess``, the body at rest."""
    from .scene import load_scene

    kwargs = {} if dtype is None else {"dtype": dtype}
    return load_scene(scene_spec(case, preset, guess, velocity=(0.0, 0.0, 0.0)), **kwargs)


def fit_config(case: Case, preset: Preset, **options):
    """The :class:`~jaxmpm.fit.FitConfig` the harness fits ``case`` with (silhouettes: the
    silhouette term with RGB at 0.1, the preset's pixels per view); ``options``: further fields."""
    from .fit import FitConfig

    weights = None if case.supervision == "tracks" else {"silhouette": 1.0, "rgb": 0.1}
    return FitConfig(weights=weights, max_steps=preset.max_steps, num_pixels=preset.pixels, colors=None, **options)


def run_case(case: Case, preset: Preset, dtype: str = "float32", guess: dict | None = None,
             resolution: bool = False, refine_velocity: bool | None = None,
             scan: Sequence[float] | None = None) -> dict:
    """Generate the ground truth of ``case``, observe it, identify it; return a result row.

    ``dtype``: ``"float32"`` or ``"float64"`` (which needs JAX's x64 mode, enabled by the
    caller: the harness's subprocess does), for the ground truth and the fit alike. ``guess``: the material's starting values (default: PAC-NeRF's initial
    guesses, :data:`INITIAL_GUESS`). ``resolution``, ``refine_velocity``, ``scan``: those of
    :class:`jaxmpm.fit.FitConfig` (``refine_velocity``: None refits the velocity with the
    material when it rests on one interval of silhouettes, False holds it after its
    pre-contact stage as PAC-NeRF's protocol does, True always refits it; ``scan``: decade
    offsets tried before the first stage that fits a log10 parameter, None the automatic
    choice, which scans silhouette fits only, ``()`` none: PAC-NeRF's protocol)."""
    import jax

    if dtype not in ("float32", "float64"):
        raise ValueError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
    if dtype == "float64" and not jax.config.jax_enable_x64:
        raise ValueError("dtype 'float64' needs jax.config.update('jax_enable_x64', True) first")
    import jax.numpy as jnp

    jdtype = jnp.dtype(dtype)

    from .fit import fit

    t0 = time.perf_counter()
    observed = observe_case(case, preset, jdtype)
    if isinstance(observed, str):
        return {"case": asdict(case), "key": case.key, "error": observed}
    obs, truth, v0, gt = observed
    generate_s = time.perf_counter() - t0

    guess = dict(INITIAL_GUESS[case.material] if guess is None else guess)
    start = start_scene(case, preset, guess, jdtype)
    names = FIT_NAMES[case.material] + ["velocity"]
    t0, c0 = time.perf_counter(), time.process_time()
    config = fit_config(case, preset, resolution=resolution, refine_velocity=refine_velocity,
                        scan=None if scan is None else tuple(float(d) for d in scan))
    result = fit(start.model, start.params, obs, names, config, **fit_reporters(t0))
    seconds, cpu_seconds = time.perf_counter() - t0, time.process_time() - c0
    err = errors(FIT_NAMES[case.material], result.values, truth)
    v_err = float(np.linalg.norm(np.asarray(result.values["velocity"], float) - np.asarray(v0)))
    return {
        "case": asdict(case),
        "key": case.key,
        "particles": int(gt.model.num_particles),
        "truth": truth,
        "initial": guess,
        "estimate": {k: np.asarray(v).tolist() for k, v in result.values.items()},
        "std": {k: np.asarray(v).tolist() for k, v in result.std.items()},
        "errors": err,
        "velocity_error": v_err,
        "converged": bool(result.converged),
        "message": result.message,
        "iterations": int(result.iterations),
        "seconds": seconds,
        "cpu_seconds": cpu_seconds,
        "generate_seconds": generate_s,
        "load_average": os.getloadavg()[0],
        "substeps": int(result.substeps),
        "stages": [{k: s[k] for k in ("label", "iterations", "converged", "seconds")} for s in result.stages],
        "other_start": result.timing.get("other_start"),  # the start not kept, where the fit ran from two
        "dtype": dtype,
        "resolution": resolution,
        "refine_velocity": refine_velocity,
        "scan": _scan_text(scan),
        "code": code_version(),
    }


def _child(argv: list[str]) -> None:
    case = Case(**json.loads(argv[0]))
    preset = Preset(**json.loads(argv[1]))
    if argv[2] == "float64":  # this subprocess is the harness's: its precision is the run's choice
        import jax

        jax.config.update("jax_enable_x64", True)
    try:
        row = run_case(case, preset, argv[2], **json.loads(argv[3]))
    except Exception as err:  # a failed case is a result too
        row = {"case": asdict(case), "key": case.key, "error": f"{type(err).__name__}: {err}"}
    row["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print("SYSID-JSON " + json.dumps(row))


def _run_child(case: Case, preset: Preset, timeout: float | None, log: Path, dtype: str = "float32",
               options: dict | None = None) -> dict:
    """Run one case in a subprocess (``options``: :func:`run_case`'s keyword options); its
    terminal output (the fit's progress) streams to ``log``, so a case that times out or crashes
    leaves its progress behind."""
    cmd = [sys.executable, "-c", "import sys; from jaxmpm.bench_sysid import _child; _child(sys.argv[1:])",
           json.dumps(asdict(case)), json.dumps(asdict(preset)), dtype, json.dumps(options or {})]
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as fh:
        try:
            proc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            return {"case": asdict(case), "key": case.key, "error": f"timed out after {timeout:.0f} s (log: {log})"}
    lines = log.read_text().splitlines()
    for line in lines:
        if line.startswith("SYSID-JSON "):
            return json.loads(line[len("SYSID-JSON "):])
    tail = [ln for ln in lines if ln.strip()][-3:]
    return {"case": asdict(case), "key": case.key,
            "error": f"failed (exit {proc.returncode}): " + " | ".join(tail) + f" (log: {log})"}


# --------------------------------------------------------------------------- the table


def _fmt_ms(values, digits=3):
    values = [v for v in values if v is not None and np.isfinite(v)]
    if not values:
        return "–"
    if len(values) == 1:
        return f"{values[0]:.{digits}f}"
    return f"{np.mean(values):.{digits}f} ± {np.std(values):.{digits}f}"


PARAM_COLUMNS = ("mu", "kappa", "yield_stress", "eta", "E", "nu", "friction_angle")
PARAM_HEADERS = {"mu": "μ", "kappa": "κ", "yield_stress": "τ_Y", "eta": "η", "E": "E", "nu": "ν",
                 "friction_angle": "φ (°)"}


def summarise(rows: list[dict]) -> str:
    """A markdown table: per (supervision, mode, material, collider) group, mean ± std of the
    errors (|Δlog10| for μ κ τ_Y η E; |Δ| for ν and φ), converged count, s per
    identification and peak RSS."""
    groups: dict[tuple, list[dict]] = {}
    failed = []
    for r in rows:
        if "error" in r:
            failed.append(r)
            continue
        c = r["case"]
        groups.setdefault((c["supervision"], c["mode"], c["material"], c["collider"]), []).append(r)
    head = ["supervision", "mode", "material", "collider", "n", "conv."] + [PARAM_HEADERS[p] for p in PARAM_COLUMNS] + \
        ["‖Δv‖ m/s", "wall s / id", "CPU s / id", "peak MB"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    order = {m: i for i, m in enumerate(MATERIALS)}
    for key in sorted(groups, key=lambda k: (SUPERVISION.index(k[0]), MODES.index(k[1]), order[k[2]], k[3])):
        rs = groups[key]
        cells = list(key) + [str(len(rs)), f"{sum(r['converged'] for r in rs)}/{len(rs)}"]
        for p in PARAM_COLUMNS:
            vals = [r["errors"][p] for r in rs if p in r["errors"]]
            cells.append(_fmt_ms(vals, 2 if p == "friction_angle" else 3) if vals else "")
        cells.append(_fmt_ms([r["velocity_error"] for r in rs], 3))
        cells.append(_fmt_ms([r["seconds"] for r in rs], 0))
        cells.append(_fmt_ms([r.get("cpu_seconds") for r in rs], 0))
        cells.append(_fmt_ms([r["peak_rss_mb"] for r in rs], 0))
        lines.append("| " + " | ".join(cells) + " |")
    if failed:
        lines.append("")
        lines += [f"* failed: `{r['key']}`: {r['error']}" for r in failed]
    return "\n".join(lines)


def targets(rows: list[dict]) -> str:
    """Met/missed against the targets: tracks |Δlog10| ≤ 0.02 (μ, τ_Y, η, E), φ ≤ 0.3°;
    silhouettes ≤ 0.05 and ≤ 0.5° (CPIC cases)."""
    out = []
    for sup, lim_log, lim_deg in (("tracks", 0.02, 0.3), ("silhouettes", 0.05, 0.5)):
        rs = [r for r in rows if "error" not in r and r["case"]["supervision"] == sup and r["case"]["mode"] == "cpic"]
        if not rs:
            continue
        for p in ("mu", "yield_stress", "eta", "E", "friction_angle"):
            vals = [r["errors"][p] for r in rs if p in r["errors"]]
            if not vals:
                continue
            lim = lim_deg if p == "friction_angle" else lim_log
            ok = sum(v <= lim for v in vals)
            out.append(f"* {sup}, {PARAM_HEADERS[p]}: {ok}/{len(vals)} cases within {lim:g} "
                       f"(median {np.median(vals):.3g}, max {np.max(vals):.3g})")
    return "\n".join(out)


def sigma_check(rows: list[dict]) -> str:
    """How far the truth lies from each estimate in units of its reported σ, ``|estimate −
    truth| / σ`` per fitted parameter, by supervision, mode, convergence and the kind of σ
    (Gauss–Newton, or resolved: ``--resolution``): count, median, how many within 3σ. (The
    benchmark's observations are noise-free, so the Gauss–Newton σ reflects round-off and
    misfit, not an error bar; see docs/fitting.md.)"""
    groups: dict[tuple, list[float]] = {}
    for r in rows:
        if "error" in r:
            continue
        for p in r["errors"]:
            sd = r.get("std", {}).get(p)
            if sd is None or not np.isscalar(sd) or not sd > 0:
                continue
            z = abs(float(r["estimate"][p]) - float(r["truth"][p])) / float(sd)
            key = (r["case"]["supervision"], r["case"]["mode"], "converged" if r["converged"] else "not converged",
                   ", resolved σ" if r.get("resolution") else "")
            groups.setdefault(key, []).append(z)
    out = []
    for (sup, mode, conv, kind), zs in sorted(groups.items()):
        z = np.asarray(zs)
        out.append(f"* {sup}, {mode}, {conv}{kind}: {len(z)} parameter estimates, truth at a median of "
                   f"{np.median(z):.3g} σ (max {z.max():.3g}); {int(np.sum(z <= 3))} within 3σ")
    return "\n".join(out)


def _scan_text(scan) -> str:
    """A ``scan`` choice as ``--scan`` spells it: None "auto", empty "none", else the offsets."""
    if scan is None:
        return "auto"
    if isinstance(scan, str):
        return scan
    return ",".join(f"{float(d):g}" for d in scan) or "none"


def _choices(row: dict) -> dict[str, str]:
    """A row's run-wide choices, as its command line spells them: the dtype, the
    ``--refine-velocity`` choice (rows before session 33 held the velocity: "no") and the
    ``--scan`` choice (rows before session 34 scanned nothing: "none")."""
    from .fit import REFINE_VELOCITY

    refine = row.get("refine_velocity", False)
    return {"dtype": row.get("dtype", "float32"),
            "--refine-velocity": next(k for k, v in REFINE_VELOCITY.items() if v is refine),
            "--scan": _scan_text(row.get("scan", "none"))}


def run_sysid_bench(argv: list[str] | None = None) -> int:
    """Entry point of ``jaxmpm bench sysid`` (see the module docstring). Returns an exit code."""
    from .cli import parse_scan
    from .errors import JaxmpmError
    from .fit import REFINE_VELOCITY

    parser = argparse.ArgumentParser(prog="jaxmpm bench sysid", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", choices=("ci", "reduced", "full"), default="reduced")
    parser.add_argument("--out", default="bench_sysid", help="output folder (results.jsonl, table.md)")
    parser.add_argument("--only", default=None, help="comma-separated substrings of case keys to run")
    parser.add_argument("--limit", type=int, default=None, help="run at most this many new cases")
    parser.add_argument("--timeout", type=float, default=None, help="seconds per case (default: none)")
    parser.add_argument("--list", action="store_true", help="list the cases and exit")
    parser.add_argument("--float64", action="store_true",
                        help="simulate the ground truths and fit in float64 (to tell a rough loss from rounding); "
                             "an output folder holds rows of one dtype")
    parser.add_argument("--resolution", action="store_true",
                        help="standard deviations raised to the scale each loss resolves (FitConfig.resolution; "
                             "the σ check then tests those)")
    parser.add_argument("--refine-velocity", choices=tuple(REFINE_VELOCITY), default="auto",
                        help="refit the initial velocity with the material after its pre-contact stage: auto "
                             "(when it rests on one interval of silhouettes), yes, or no (held: PAC-NeRF's "
                             "protocol, and this harness's before session 33); FitConfig.refine_velocity. "
                             "An output folder holds rows of one choice")
    parser.add_argument("--scan", default="auto", metavar="DECADES",
                        help="before the first stage that fits a log10 parameter, try its value x 10^d for these "
                             "d and start from the best (FitConfig.scan): auto (default; -1,1,2,3 for the "
                             "silhouette cases, none for the track cases), none (PAC-NeRF's protocol, and this "
                             "harness's before session 34) or offsets. An output folder holds rows of one choice")
    args = parser.parse_args(argv)
    refine_velocity = REFINE_VELOCITY[args.refine_velocity]
    dtype = "float64" if args.float64 else "float32"
    try:
        scan = parse_scan(args.scan)
    except JaxmpmError as err:
        parser.error(str(err))
    preset, cases = preset_cases(args.preset)
    if args.only:
        keys = [k.strip() for k in args.only.split(",") if k.strip()]
        cases = [c for c in cases if any(k in c.key for k in keys)]
    if args.list:
        for c in cases:
            print(c.key)
        print(f"{len(cases)} cases; preset {asdict(preset)}")
        return 0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = out / "results.jsonl"
    done = {}
    if results.exists():
        for line in results.read_text().splitlines():
            if line.strip():
                row = json.loads(line)
                done[row["key"]] = row
    wanted = _choices({"dtype": dtype, "refine_velocity": refine_velocity, "scan": _scan_text(scan)})
    for name, value in wanted.items():
        held = sorted({_choices(r)[name] for r in done.values() if "error" not in r} - {value})
        if held:
            what = f"{', '.join(held)} rows" if name == "dtype" else f"rows of {name} {', '.join(held)}"
            run = value if name == "dtype" else f"{name} {value}"
            print(f"error: {results} holds {what}; run {run} into another --out", file=sys.stderr)
            return 2
    todo = [c for c in cases if c.key not in done]
    if args.limit is not None:
        todo = todo[: args.limit]
    print(f"{len(cases)} cases ({len(cases) - len(todo)} done), preset {args.preset} in {dtype}: dx = {preset.dx}, "
          f"{preset.substeps} substeps/frame, {preset.frames} frames, {preset.views} views at {preset.res} px",
          file=sys.stderr, flush=True)
    for i, case in enumerate(todo):
        print(f"[{i + 1}/{len(todo)}] {case.key} ...", file=sys.stderr, flush=True)
        row = _run_child(case, preset, args.timeout, out / "logs" / f"{case.key}.log", dtype,
                         {"resolution": args.resolution, "refine_velocity": refine_velocity, "scan": scan})
        done[case.key] = row
        with open(results, "a") as fh:
            fh.write(json.dumps(row) + "\n")
        if "error" in row:
            print(f"    failed: {row['error']}", file=sys.stderr, flush=True)
        else:
            errs = ", ".join(f"{k} {v:.3g}" for k, v in row["errors"].items())
            print(f"    {errs}; {row['seconds']:.0f} s, {row['peak_rss_mb']:.0f} MB, "
                  f"{'converged' if row['converged'] else 'NOT converged'}", file=sys.stderr, flush=True)
    rows = [done[c.key] for c in cases if c.key in done]
    table = summarise(rows)
    text = (f"preset {args.preset}: {asdict(preset)}\n\n{table}\n\nTargets:\n{targets(rows)}\n\n"
            f"Truth against the reported σ:\n{sigma_check(rows)}\n")
    (out / "table.md").write_text(text)
    print(text)
    return 0 if rows and all("error" not in r for r in rows) else 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(run_sysid_bench(sys.argv[1:]))

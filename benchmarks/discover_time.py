"""How long `jaxmpm discover` takes on a 2D case of ~1,500 particles and 6,000 steps (issue 15,
target 4: <= 10 min on 2 idle cores).

A 2D elastic block (E = 3 kPa or ``--E``, dx = 9 mm, ppc 4: 1,452 particles) thrown at
(1.5, 0.5) m/s (``--velocity``) onto a slip floor (``--contact sticky``), 60 frames x 100
substeps, tracked with 1 mm noise; the block's bottom starts ``--height`` (0.1 m) above the
floor; the data hide a gravity error (delta g = (0, -2) m/s^2 or ``--delta``, ``--hidden
gravity``), Coulomb friction on the floor (``--hidden friction --friction 0.3``) or nothing
(``--hidden none``, the control) or air drag in free flight (``--hidden drag --drag 0.3``:
linear drag k1 in 1/s; with ``--frame-dt`` and ``--height`` chosen so that the block never
lands, the case is smooth in the hidden effect and converged in dt). `discover`
gets the base scene only and runs with its defaults (top 3 refits, greedy steps, the dt/2
check). Prints the verdict, the cause, the held-out gain, the wall and CPU seconds.

The 3D case (``--dim 3``): the same block, 0.2 m deep along z (``--dx 0.01``, ppc 8: 48,000
particles), on the same floor.

    PYTHONPATH=. python benchmarks/discover_time.py [--hidden gravity|none] [--delta 1,0] [--json out.json]
        [--E 3e4 --velocity 0.5,0 --contact sticky]   # a case converged in dt (dt/2 moves it 7 mm)
        [--hidden drag --frames 24 --substeps 250 --frame-dt 0.01667 --velocity 1,1.5]   # free flight
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def scene_arguments(ap: argparse.ArgumentParser) -> None:
    """The scene's command-line options (shared with discover_linearity.py)."""
    ap.add_argument("--dim", type=int, default=2, choices=(2, 3), help="2D, or 3D (the block 0.2 m deep along z)")
    ap.add_argument("--E", type=float, default=3e3, help="Young's modulus, Pa")
    ap.add_argument("--velocity", default="1.5,0.5", help="the throw, m/s (x,y)")
    ap.add_argument("--contact", default="slip", choices=("slip", "sticky"), help="the floor's contact")
    ap.add_argument("--dx", type=float, default=0.009)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--substeps", type=int, default=100)
    ap.add_argument("--height", type=float, default=0.1, help="the block's bottom above the floor, m")
    ap.add_argument("--frame-dt", type=float, default=1.0 / 24.0, help="seconds between frames")


def vector(text: str, dim: int) -> list[float]:
    """A comma-separated vector, padded with zeros to ``dim`` components (``"1,0.5"`` in 3D: (1, 0.5, 0))."""
    v = [float(c) for c in text.split(",")]
    if len(v) > dim:
        raise SystemExit(f"{text!r} has {len(v)} components; the scene is {dim}D")
    return v + [0.0] * (dim - len(v))


def block_scene(args):
    """The thrown elastic block of the module docstring, from :func:`scene_arguments`' options."""
    from scenes import block_spec

    from jaxmpm.scene import load_scene

    d = args.dim
    velocity = vector(args.velocity, d)
    spec = block_spec(d, {"model": "elastic", "E": args.E, "nu": 0.3}, dx=args.dx, frames=args.frames,
                      substeps=args.substeps,
                      floor={"point": vector("0,0.1", d), "normal": vector("0,1", d), "contact": args.contact},
                      lo=[0.2, 0.1 + args.height, 0.4][:d], hi=[0.4, 0.25 + args.height, 0.6][:d], velocity=velocity,
                      ppc=2**d)
    spec["frame_dt"] = args.frame_dt
    return load_scene(spec)


def main() -> None:
    from jaxmpm import extensions as X
    from jaxmpm.discover import _rollout, discover
    from jaxmpm.discover_report import format_timing
    from jaxmpm.observe import Observation

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--hidden", choices=("gravity", "friction", "drag", "none"), default="gravity")
    ap.add_argument("--delta", default="0,-2", help="the hidden gravity error, m/s^2 (x,y)")
    ap.add_argument("--friction", type=float, default=0.3, help="the floor's hidden Coulomb coefficient")
    ap.add_argument("--drag", type=float, default=0.3, help="the hidden linear air drag k1, 1/s")
    scene_arguments(ap)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    velocity = vector(args.velocity, args.dim)
    scene = block_scene(args)
    m, p = scene.model, scene.params
    ids = [e for e in X.EXTENSIONS if X.applicable(m, e) is None]
    delta = vector(args.delta, args.dim)
    hidden = {"gravity": {"gravity": {"delta": delta}}, "friction": {"collider_friction": {"floor": args.friction}},
              "drag": {"drag": {"linear": args.drag}}, "none": None}[args.hidden]
    truth = X.enable(m, p, ids, hidden)
    x = np.asarray(_rollout(m, truth, args.frames)[0].x, float)
    x = x + 1e-3 * np.random.default_rng(0).standard_normal(x.shape)
    obs = Observation(times=np.arange(args.frames) * m.frame_dt, positions=x, point_ids="particles")
    print(f"{m.num_particles} particles, {args.frames} frames x {args.substeps} substeps "
          f"= {args.frames * args.substeps} steps; hidden: {args.hidden}", flush=True)
    t0, c0 = time.perf_counter(), time.process_time()
    result = discover(m, p, obs, progress=lambda line: print(f"  [{time.perf_counter() - t0:7.1f} s] {line}", flush=True))
    row = {"hidden": args.hidden, "delta": delta if args.hidden == "gravity" else None,
           "friction": args.friction if args.hidden == "friction" else None,
           "drag": args.drag if args.hidden == "drag" else None, "frame_dt": args.frame_dt, "height": args.height, "E": args.E, "velocity": velocity, "dim": args.dim, "dx": args.dx,
           "contact": args.contact, "frames": args.frames, "substeps": args.substeps, "particles": int(m.num_particles), "steps": args.frames * args.substeps,
           "discrepancy": bool(result.discrepancy), "cause": result.cause, "causes": list(result.causes),
           "gain": None if result.gain is None else float(result.gain), "verdict": result.verdict,
           "parameters": {k: np.asarray(v, float).tolist() for k, v in result.parameters.items()},
           "refits": [c.id for c in result.candidates if c.refit],
           "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0, "timing": result.timing}
    print(format_timing(result))
    print(json.dumps(row))
    if args.json:
        Path(args.json).write_text(json.dumps(row, indent=2))


if __name__ == "__main__":
    main()

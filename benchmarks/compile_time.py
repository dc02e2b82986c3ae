"""Where a small run's time goes: compiling the step, and the quick video demo's stages.

    PYTHONPATH=. python benchmarks/compile_time.py step examples/bunny.toml examples/bowl.toml
    PYTHONPATH=. python benchmarks/compile_time.py video-demo [--out DIR]

``step``: per scene, the step's jaxpr size (equations), the seconds to lower and to compile
``jax.jit(step)``, and the milliseconds per call (mean of 20, compiled). ``video-demo``:
``jaxmpm demo --video --quick`` with 2 LM steps per stage (the default test suite's case),
its wall time and the fit's timing block and per-stage seconds from ``fit.json``.
Run it alone: compile and run times depend on what else the machine does.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import jax


def step_times(path: str, calls: int = 20) -> dict:
    from jaxmpm.scene import load_scene
    from jaxmpm.step import _start, step

    scene = load_scene(path)
    model, params, state = _start(scene.model, scene.params, None)
    fn = lambda s: step(model, params, s)  # noqa: E731
    equations = len(jax.make_jaxpr(fn)(state).jaxpr.eqns)
    t0 = time.perf_counter()
    lowered = jax.jit(fn).lower(state)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()
    jax.block_until_ready(compiled(state))
    t3 = time.perf_counter()
    for _ in range(calls):
        out = compiled(state)
    jax.block_until_ready(out)
    t4 = time.perf_counter()
    return {"scene": path, "particles": scene.model.num_particles, "equations": equations,
            "lower_s": round(t1 - t0, 2), "compile_s": round(t2 - t1, 2), "run_ms": round((t4 - t3) / calls * 1e3, 2)}


def video_demo(out: Path) -> dict:
    from jaxmpm.demo import run_video_demo

    t0 = time.perf_counter()
    run_video_demo(out, quick=True, max_steps=2)
    wall = time.perf_counter() - t0
    fit = json.loads((out / "identify" / "fit.json").read_text())
    return {"wall_s": round(wall, 1), "timing": fit["timing"], "params": fit["params"],
            "stages": [{"label": s["label"], "frames": s["frames"], "seconds": round(s["seconds"], 2),
                        "start_s": round(s["timing"].get("start_s", 0.0), 2)} for s in fit["stages"]]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="what", required=True)
    s = sub.add_parser("step")
    s.add_argument("scenes", nargs="+")
    v = sub.add_parser("video-demo")
    v.add_argument("--out", default=None)
    args = parser.parse_args()
    if args.what == "step":
        for path in args.scenes:
            print(json.dumps(step_times(path)))
    else:
        out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="jaxmpm-compile-"))
        print(json.dumps(video_demo(out), indent=1))


if __name__ == "__main__":
    main()

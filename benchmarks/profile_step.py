"""Where the time of one MPM step and of its gradient goes, stage by stage (XLA op profile).

    pip install xprof                     # reads jax.profiler's traces (not a jaxmpm dependency)
    python benchmarks/profile_step.py [--material corotated] [--particles 25000] [--grid 64]
                                      [--repeats 10] [--json out.json] [--tangents K] [--steps S]
                                      [--scene cube|bunny|moving]

Traces ``--repeats`` calls of (a) the jitted step and (b) the jitted gradient of a loss of
one step with respect to the parameters and the state, with :func:`jax.profiler.trace`. Every
XLA operation that ran is attributed to the step stage whose :func:`jax.named_scope` its
metadata carries (``jaxmpm.step.step`` names them: stencil, contact, material, p2g,
grid_update, g2p, advect), and to the backward pass when its metadata says ``transpose(``
(reverse mode's transposition of the forward's linearisation). Times are summed over XLA's
worker threads (CPU milliseconds per call), so the table is the cost of each stage, not the
wall time: on 2 cores the wall time is between the total / 2 and the total.

``--tangents K`` profiles forward mode instead of (b): ``jax.vmap`` of ``jax.jvp`` of the step
over K tangent directions of the parameters and the state (what a Levenberg–Marquardt
Jacobian of K parameters does at every step of a rollout), against the step itself.

``--steps S`` (S > 1) profiles a rollout of S steps (one ``lax.scan``; in the gradient every
step under ``jax.checkpoint``, as ``bench_grad.py`` does) and reports CPU ms per step. This is
what a fit runs: a single step's profile also counts first-touch costs of its freshly
allocated buffers, which a rollout's loop pays once (zero-filling the k = 6 tangent grid:
7.6 ms in one step, 0.9–1.1 ms per step of a 10-step rollout; docs/benchmarks.md, session 27).
"""

from __future__ import annotations

import argparse
import collections
import glob
import json
import re
import sys
import tempfile
import time

STAGES = ("stencil", "contact", "material", "p2g", "grid_update", "g2p", "advect")

_INSTRUCTION = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+) = .*?metadata=\{([^}]*)\}")
_OP_NAME = re.compile(r'op_name="([^"]*)"')


def op_names(hlo_text: str) -> dict[str, str]:
    """Instruction name -> its ``op_name`` metadata, from an optimised HLO module's text."""
    out = {}
    for line in hlo_text.splitlines():
        m = _INSTRUCTION.match(line)
        if m:
            name = _OP_NAME.search(m.group(2))
            if name:
                out[m.group(1)] = name.group(1)
    return out


def stage_of(op_name: str) -> tuple[str, str]:
    """``(stage, "forward" | "backward")`` of an op from its ``op_name`` metadata."""
    stage = next((s for s in STAGES if re.search(rf"(^|[/(]){s}([/)]|$)", op_name)), "outside the step")
    return stage, "backward" if "transpose(" in op_name else "forward"


def _trace_events(log_dir: str) -> list[dict]:
    try:
        from xprof.convert import raw_to_tool_data
    except ImportError:
        sys.exit("profile_step.py reads the trace with xprof: pip install xprof")
    path = glob.glob(f"{log_dir}/**/*.xplane.pb", recursive=True)[0]
    data, _ = raw_to_tool_data.xspace_to_tool_data([path], "trace_viewer", {})
    return json.loads(data)["traceEvents"]


def rollout(model, params, state, steps: int, checkpoint: bool = False):
    """The state after ``steps`` steps: the step itself when ``steps == 1``, else one
    ``lax.scan`` (each step under ``jax.checkpoint`` when ``checkpoint``)."""
    import jax

    from jaxmpm.step import step

    def one(s):
        return step(model, params, s)

    if steps == 1:
        return one(state)
    advance = jax.checkpoint(one) if checkpoint else one
    return jax.lax.scan(lambda s, _: (advance(s), None), state, None, length=steps)[0]


def profile(fn, args, repeats: int, steps: int = 1) -> tuple[dict, float, float]:
    """Per-op CPU ms of jitted ``fn(*args)``, and its wall and CPU ms, per call divided by
    ``steps`` (per step of a rollout)."""
    import jax

    compiled = jax.jit(fn).lower(*args).compile()
    names = op_names(compiled.as_text())
    jax.block_until_ready(compiled(*args))
    with tempfile.TemporaryDirectory() as log_dir:
        t0, c0 = time.perf_counter(), time.process_time()
        with jax.profiler.trace(log_dir):
            for _ in range(repeats):
                jax.block_until_ready(compiled(*args))
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        events = _trace_events(log_dir)
    per_op = collections.defaultdict(float)
    for e in events:
        op = e.get("args", {}).get("hlo_op")
        if e.get("ph") == "X" and op is not None:
            per_op[op] += e["dur"] / 1e3 / repeats / steps
    # a conditional's event spans the ops of its branch, which have their own events
    containers = set(re.findall(r"^\s*(?:ROOT\s+)?%?([\w.\-]+) = .*? conditional\(", compiled.as_text(), re.M))
    table = {op: {"ms": ms, "op_name": names.get(op, "")} for op, ms in per_op.items() if op not in containers}
    return table, 1e3 * wall / repeats / steps, 1e3 * cpu / repeats / steps


def by_stage(table: dict) -> dict:
    out = collections.defaultdict(float)
    for row in table.values():
        out[stage_of(row["op_name"])] += row["ms"]
    return dict(out)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--material", default="corotated")
    parser.add_argument("--particles", type=int, default=25_000)
    parser.add_argument("--grid", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--top", type=int, default=15, help="list the most expensive ops")
    parser.add_argument("--json", default=None)
    parser.add_argument("--tangents", type=int, default=0, help="profile forward mode with K tangents instead")
    parser.add_argument("--steps", type=int, default=1, help="profile a rollout of S steps (CPU ms per step)")
    parser.add_argument("--scene", choices=("cube", "bunny", "moving"), default="cube",
                        help="cube: the peers' cube (--material, --particles, --grid); bunny: "
                             "bench_colliders.py's CPIC cost scene (25k fluid particles on the bunny); "
                             "moving: the same with the bunny moving at 0.05 m/s")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.repeats < 1 or args.tangents < 0:
        parser.error("--steps and --repeats must be >= 1, --tangents >= 0")

    import jax
    import jax.numpy as jnp

    from jaxmpm.bench import _scene_model
    from jaxmpm.model import initial_state
    from jaxmpm.step import step

    if args.scene == "cube":
        model, params = _scene_model(args.particles, args.grid, args.material, jnp.float32)
    else:
        model, params = _bunny_scene(moving=args.scene == "moving")
    state = initial_state(model, params)
    advance = jax.jit(lambda s: step(model, params, s))
    for _ in range(5):  # a state with nonzero C and F != I
        state = advance(state)

    def forward(params, state):
        return rollout(model, params, state, args.steps)

    def loss(params, state):
        return jnp.mean(rollout(model, params, state, args.steps, checkpoint=True).x ** 2)

    gradient = jax.grad(loss, argnums=(0, 1), allow_int=True)
    fwd, fwd_wall, fwd_cpu = profile(forward, (params, state), args.repeats, args.steps)
    if args.tangents:
        return _report_tangents(args, model, params, state, fwd, fwd_wall, fwd_cpu)
    bwd, bwd_wall, bwd_cpu = profile(gradient, (params, state), args.repeats, args.steps)

    f_stage, b_stage = by_stage(fwd), by_stage(bwd)
    _print_header(args, model)
    print("| stage | step: forward | gradient: forward part | gradient: backward part | backward ÷ forward |")
    print("|---|---|---|---|---|")
    for s in (*STAGES, "outside the step"):
        f, gf, gb = f_stage.get((s, "forward"), 0.0), b_stage.get((s, "forward"), 0.0), b_stage.get((s, "backward"), 0.0)
        if f or gf or gb:
            print(f"| {s} | {f:.2f} | {gf:.2f} | {gb:.2f} | {gb / f if f else float('nan'):.1f} |")
    f_sum = sum(r["ms"] for r in fwd.values())
    print(f"| **total in ops** | {f_sum:.2f} | {sum(v for (s, d), v in b_stage.items() if d == 'forward'):.2f} | "
          f"{sum(v for (s, d), v in b_stage.items() if d == 'backward'):.2f} | |")
    print(f"\nprocess: step {fwd_wall:.2f} ms wall / {fwd_cpu:.2f} ms CPU; gradient {bwd_wall:.2f} ms wall / "
          f"{bwd_cpu:.2f} ms CPU {_per(args)} (gradient ÷ step: {bwd_cpu / fwd_cpu:.1f}x CPU)")
    _print_top_ops(bwd, args.top, "the gradient")
    _write_json(args, fwd, "gradient", bwd, [fwd_wall, bwd_wall], [fwd_cpu, bwd_cpu])
    return 0


def _bunny_scene(moving: bool = False):
    """``bench_colliders.py``'s CPIC cost scene: 25,000 fluid particles resting on the bunny
    (``moving``: the bunny translating at 0.05 m/s, so its field is read in its rest frame)."""
    from pathlib import Path

    import numpy as np
    from bench_colliders import cost_points, cost_scene

    from jaxmpm.scene import load_scene

    with tempfile.TemporaryDirectory() as tmp:
        points = Path(tmp) / "fluid.npy"
        np.save(points, cost_points())
        spec = cost_scene("cpic", points)
        if moving:
            spec["colliders"][1]["velocity"] = [0.0, 0.05, 0.0]
        scene = load_scene(spec)
    return scene.model, scene.params


def _per(args) -> str:
    return "per call" if args.steps == 1 else f"per step of a {args.steps}-step rollout"


def _print_header(args, model, extra: str = "") -> None:
    what = {"cube": args.material, "bunny": "CPIC: fluid on the bunny",
            "moving": "CPIC: fluid on the moving bunny"}[args.scene]
    grid = "x".join(str(n) for n in model.grid.shape)
    print(f"{what}, {model.num_particles} particles, {grid} grid, float32; CPU ms {_per(args)} "
          f"(summed over XLA's threads), {args.repeats} calls{extra}\n")


def _print_top_ops(table: dict, top: int, what: str) -> None:
    """The ``top`` most expensive ops of a profile ``table``, with their stage and pass."""
    print(f"\nthe {top} most expensive ops of {what}:\n")
    print("| CPU ms | op | stage | pass | op_name |")
    print("|---|---|---|---|---|")
    for op, row in sorted(table.items(), key=lambda kv: -kv[1]["ms"])[:top]:
        stage, direction = stage_of(row["op_name"])
        print(f"| {row['ms']:.2f} | {op} | {stage} | {direction} | {row['op_name'][-90:]} |")


def _write_json(args, fwd: dict, name: str, other: dict, wall_ms: list, cpu_ms: list) -> None:
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"args": vars(args), "forward": fwd, name: other, "wall_ms": wall_ms, "cpu_ms": cpu_ms}, fh, indent=1)


def _report_tangents(args, model, params, state, fwd, fwd_wall, fwd_cpu) -> int:
    """``--tangents K``: the step's forward-mode cost by stage against the step's."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    dynamic, static = eqx.partition(state, eqx.is_inexact_array)
    leaves, treedef = jax.tree_util.tree_flatten((params, dynamic))
    keys = jax.random.split(jax.random.PRNGKey(0), len(leaves))
    # K random tangent directions of every float input (parameters and state)
    tangents = treedef.unflatten([1e-3 * jax.random.normal(k, (args.tangents, *jnp.shape(a)), jnp.result_type(a))
                                  for k, a in zip(keys, leaves)])

    def push(params, dynamic, tangents):
        def out(p, d):
            return eqx.partition(rollout(model, p, eqx.combine(d, static), args.steps), eqx.is_inexact_array)[0]

        return jax.vmap(lambda t: jax.jvp(out, (params, dynamic), t)[1])(tangents)

    tan, tan_wall, tan_cpu = profile(push, (params, dynamic, tangents), args.repeats, args.steps)
    f_stage, t_stage = by_stage(fwd), by_stage(tan)
    _print_header(args, model, f"; forward mode with {args.tangents} tangents")
    print("| stage | step | jvp of the step (primal + tangents) | jvp ÷ step |")
    print("|---|---|---|---|")
    for s in (*STAGES, "outside the step"):
        f, t = f_stage.get((s, "forward"), 0.0), t_stage.get((s, "forward"), 0.0)
        if f or t:
            print(f"| {s} | {f:.2f} | {t:.2f} | {t / f if f else float('nan'):.1f} |")
    f_sum, t_sum = sum(r["ms"] for r in fwd.values()), sum(r["ms"] for r in tan.values())
    print(f"| **total in ops** | {f_sum:.2f} | {t_sum:.2f} | {t_sum / f_sum:.1f} |")
    print(f"\nprocess: step {fwd_wall:.2f} ms wall / {fwd_cpu:.2f} ms CPU; jvp {tan_wall:.2f} ms wall / "
          f"{tan_cpu:.2f} ms CPU {_per(args)}")
    _print_top_ops(tan, args.top, "the jvp")
    _write_json(args, fwd, "jvp", tan, [fwd_wall, tan_wall], [fwd_cpu, tan_cpu])
    return 0


if __name__ == "__main__":
    sys.exit(main())

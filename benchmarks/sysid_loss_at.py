"""A sysid case's loss at chosen points: the truth, single parameters moved from it, other points.

A case of ``jaxmpm bench sysid`` (``--case``, a key of ``--preset``) is simulated at its true
values and observed as the harness observes it (tracks, or the rig's masks and images); the
loss the harness's fit minimises (same weights, pixels and renderer; all frames or those up to
``--until`` s, at the case's substeps) is then evaluated at

* the truth;
* ``--offset NAME=d1,d2,...``: the truth with one parameter moved, by ``d`` decades for a
  log10 parameter (``eta``, ``mu``, ...) or by ``d`` m/s for a velocity component
  (``velocity.x``, ``velocity.y``, ``velocity.z``); repeatable;
* ``--at 'LABEL={"eta": 8.18, "velocity": [0, -0.98, 0]}'``: absolute values (names left out
  stay at the truth), e.g. a fit's end; repeatable;
* ``--line A,B,N``: N points evenly between two labelled points (``truth`` or an ``--at``
  label), log10 parameters interpolated in log10, the velocity linearly.

One JSON line per point (label, values, loss), to ``--out`` as well. Where the fit's end has a
higher loss than the truth, these show whether the truth lies in a basin a local fit can reach
(the loss falls steadily towards it) or in a narrow well it cannot (moves of a fraction of the
parameters' targets change the loss by factors).

    python benchmarks/sysid_loss_at.py --case viscoplastic-armadillo-0-silhouettes-cpic \\
        --offset velocity.y=0.0005,-0.0005 --offset eta=0.02,-0.02 \\
        --at 'fit={"eta": 8.18, "velocity": [-0.003, -0.983, -0.0007]}' --line fit,truth,5 [--out F.jsonl]
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

AXES = {"x": 0, "y": 1, "z": 2}


def parse_offset(text: str) -> tuple[str, list[float]]:
    name, _, values = text.partition("=")
    if not values:
        raise ValueError(f"--offset {text!r}: expected NAME=d1,d2,...")
    return name.strip(), [float(v) for v in values.split(",")]


def parse_at(text: str) -> tuple[str, dict]:
    label, _, values = text.partition("=")
    if not values:
        raise ValueError(f"--at {text!r}: expected LABEL=JSON")
    point = json.loads(values)
    if not isinstance(point, dict):
        raise ValueError(f"--at {text!r}: the values must be a JSON object")
    return label.strip(), point


def moved(truth: dict, name: str, d: float, log10_names) -> dict:
    """``truth`` with ``name`` moved by ``d`` (decades for a log10 parameter, m/s for a
    velocity component ``velocity.<axis>``)."""
    point = {k: (list(v) if isinstance(v, (list, tuple)) else v) for k, v in truth.items()}
    if name.startswith("velocity."):
        axis = AXES.get(name.split(".", 1)[1])
        if axis is None:
            raise ValueError(f"unknown velocity component {name!r}: use velocity.x, velocity.y or velocity.z")
        point["velocity"][axis] += d
    elif name in log10_names and name in point:
        point[name] = point[name] * 10.0 ** d
    else:
        raise ValueError(f"cannot move {name!r}: not a fitted log10 parameter of this case, nor a velocity component")
    return point


def between(a: dict, b: dict, f: float, log10_names) -> dict:
    """The point a fraction ``f`` of the way from ``a`` to ``b``."""
    out = {}
    for k in a:
        if k in log10_names:
            out[k] = float(10.0 ** ((1 - f) * np.log10(a[k]) + f * np.log10(b[k])))
        else:
            out[k] = ((1 - f) * np.asarray(a[k], float) + f * np.asarray(b[k], float)).tolist()
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--case", required=True)
    parser.add_argument("--preset", default="reduced", choices=("ci", "reduced", "full"))
    parser.add_argument("--offset", action="append", default=[], help="NAME=d1,d2,... (repeatable)")
    parser.add_argument("--at", action="append", default=[], help="LABEL=JSON of values (repeatable)")
    parser.add_argument("--line", action="append", default=[], help="A,B,N: N points from A to B (repeatable)")
    parser.add_argument("--until", type=float, default=None, help="last observed time in the loss, s (default: all)")
    parser.add_argument("--out", default=None, help="JSON lines of the points and their losses")
    args = parser.parse_args(argv)
    try:
        offsets = [parse_offset(t) for t in args.offset]
        named = dict(parse_at(t) for t in args.at)
        lines = []
        for t in args.line:
            a, b, n = t.split(",")
            lines.append((a, b, int(n)))
    except ValueError as err:
        parser.error(str(err))

    import jax.numpy as jnp

    from jaxmpm.bench_sysid import FIT_NAMES, find_case, fit_config, observe_case, start_scene
    from jaxmpm.identify import build_objective
    from jaxmpm.identify.parameters import LOG10_PARAMS, apply_unconstrained, to_unconstrained

    try:
        preset, case = find_case(args.case, args.preset)
    except ValueError as err:
        parser.error(str(err))
    names = FIT_NAMES[case.material]
    log10_names = [n for n in names if n in LOG10_PARAMS]
    observed = observe_case(case, preset)
    if isinstance(observed, str):
        print(observed, file=sys.stderr)
        return 1
    obs, truth_values, velocity, _ = observed
    truth = {n: float(truth_values[n]) for n in names} | {"velocity": list(velocity)}
    points = {"truth": truth} | {label: truth | v for label, v in named.items()}
    for a, b, _ in lines:
        for end in (a, b):
            if end not in points:
                parser.error(f"--line: {end!r} is neither 'truth' nor an --at label")
    todo = [("truth", truth)]
    todo += [(f"{n} {d:+g}", moved(truth, n, d, log10_names)) for n, ds in offsets for d in ds]
    todo += [(label, points[label]) for label in named]
    todo += [(f"{a} -> {b} {i / (n - 1):.3g}", between(points[a], points[b], i / (n - 1), log10_names))
             for a, b, n in lines for i in range(n)]

    start = start_scene(case, preset, {n: truth[n] for n in names})
    config = fit_config(case, preset)
    objective = build_objective(start.model, obs, until=args.until, **config.objective_options())
    rows = []
    for label, point in todo:
        t0 = time.perf_counter()
        y = {n: to_unconstrained(n, jnp.asarray(v, jnp.float32)) for n, v in point.items()}
        loss = float(objective.loss(apply_unconstrained(start.model, start.params, list(y), y)))
        row = {"case": args.case, "label": label, "values": point, "loss": loss, "frames": objective.frames,
               "until": args.until, "seconds": time.perf_counter() - t0}
        rows.append(row)
        print(f"{label:>32}  loss {loss:.6g}", flush=True)
    if args.out:
        with open(args.out, "w") as f:
            f.writelines(json.dumps(r) + "\n" for r in rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())

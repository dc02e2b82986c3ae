"""One sysid case identified from several starting points: how far its answer depends on where
the fit starts.

A case of ``jaxmpm bench sysid`` (``--case``) is identified once per offset in ``--offsets``:
its log10 parameters start at PAC-NeRF's initial guesses moved by that many decades (the
linear ones, ν and the friction angle, stay). On a smooth loss every start ends at the same
point; on a rough one (CPIC's discrete decisions, ``benchmarks/sysid_landscape.py``) the
answers scatter, and their spread is the precision the case really has. Rows (the harness's,
plus ``start_offset``) are appended to ``--out``.

    python benchmarks/sysid_starts.py --case newtonian-small-0-tracks-cpic --offsets -0.5,-0.25,0,0.25,0.5 \\
        [--float64] [--resolution] --out starts.jsonl
"""

from __future__ import annotations

import argparse
import json
import sys


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--case", default="newtonian-small-0-tracks-cpic")
    parser.add_argument("--preset", default="reduced", choices=("ci", "reduced", "full"))
    parser.add_argument("--offsets", default="-0.5,0,0.5", help="comma-separated decades added to the log10 guesses")
    parser.add_argument("--float64", action="store_true")
    parser.add_argument("--resolution", action="store_true", help="FitConfig.resolution: the std the loss resolves")
    parser.add_argument("--out", required=True, help="JSON lines, one row per start")
    args = parser.parse_args(argv)
    offsets = [float(s) for s in args.offsets.split(",") if s.strip()]
    if args.float64:
        import jax

        jax.config.update("jax_enable_x64", True)

    from jaxmpm.bench_sysid import INITIAL_GUESS, find_case, run_case
    from jaxmpm.identify.parameters import LOG10_PARAMS

    try:
        preset, case = find_case(args.case, args.preset)
    except ValueError as err:
        parser.error(str(err))
    dtype = "float64" if args.float64 else "float32"
    for offset in offsets:
        guess = {k: v * 10.0**offset if k in LOG10_PARAMS else v for k, v in INITIAL_GUESS[case.material].items()}
        print(f"start {offset:+.3g} decades: {guess}", file=sys.stderr, flush=True)
        row = run_case(case, preset, dtype, guess=guess, resolution=args.resolution)
        row["start_offset"] = offset
        with open(args.out, "a") as fh:
            fh.write(json.dumps(row) + "\n")
        errs = ", ".join(f"{k} {v:.3g}" for k, v in row.get("errors", {}).items())
        print(f"  -> {errs}; {row.get('iterations')} iterations, "
              f"{'converged' if row.get('converged') else 'NOT converged'}: {row.get('message', row.get('error'))}",
              file=sys.stderr, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

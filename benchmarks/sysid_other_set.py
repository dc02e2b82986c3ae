"""Sysid cases of another truth set than the preset's, under each velocity and scan choice: a
check of a fitting rule on cases it was not chosen on.

The ``reduced`` preset holds set 0 of the silhouette cases only. This script identifies
``material-collider-SET-supervision-mode`` cases (``--cases``, the harness's key layout, any
set) with the ``reduced`` preset's settings, once per ``--refine-velocity`` choice
(:attr:`jaxmpm.fit.FitConfig.refine_velocity`: auto, yes, no) and ``--scan`` choice
(:attr:`jaxmpm.fit.FitConfig.scan`: ``auto``, ``none`` or decade offsets, choices separated by
``;``), and appends the harness's rows to ``--out``. Session 33 chose the automatic velocity refit on set 0
and checked it on set 1 with:

    python benchmarks/sysid_other_set.py --cases sand-bunny-1-silhouettes-cpic,newtonian-armadillo-1-silhouettes-cpic \\
        --refine-velocity auto,no --out other_set.jsonl

and session 34 the decade scan with ``--refine-velocity auto --scan "none;-1,1,2,3"`` (write
``--scan=-1,1,2,3`` for offsets alone: argparse reads a leading ``-1`` as an option).
"""

from __future__ import annotations

import argparse
import json
import sys


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", required=True, help="comma-separated keys material-collider-set-supervision-mode")
    parser.add_argument("--refine-velocity", default="auto,no", help="comma-separated choices among auto, yes, no")
    parser.add_argument("--scan", default="auto", help="';'-separated choices: auto, none or comma-separated decades")
    parser.add_argument("--out", required=True, help="JSON lines, one row per case and choice")
    args = parser.parse_args(argv)

    from jaxmpm.bench_sysid import COLLIDER_TOP, MATERIALS, MODES, SUPERVISION, Case, preset_cases, run_case
    from jaxmpm.cli import parse_scan
    from jaxmpm.errors import JaxmpmError
    from jaxmpm.fit import REFINE_VELOCITY

    preset, _ = preset_cases("reduced")
    cases = []
    for key in [k.strip() for k in args.cases.split(",") if k.strip()]:
        parts = key.split("-")
        if (len(parts) != 5 or parts[0] not in MATERIALS or parts[1] not in COLLIDER_TOP or not parts[2].isdigit()
                or parts[3] not in SUPERVISION or parts[4] not in MODES):
            parser.error(f"case {key!r}: expected material-collider-set-supervision-mode, e.g. sand-bunny-1-silhouettes-cpic")
        cases.append(Case(parts[0], parts[1], int(parts[2]), parts[3], parts[4]))
    choices = [c.strip() for c in args.refine_velocity.split(",") if c.strip()]
    if not choices or any(c not in REFINE_VELOCITY for c in choices):
        parser.error(f"--refine-velocity: choices among {', '.join(REFINE_VELOCITY)}, got {args.refine_velocity!r}")
    scans = {}
    for text in [t.strip() for t in args.scan.split(";") if t.strip()]:
        try:
            scans[text] = parse_scan(text)
        except JaxmpmError as err:
            parser.error(str(err))
    for case in cases:
        for choice, (scan_text, scan) in [(c, s) for c in choices for s in scans.items()]:
            print(f"{case.key}, --refine-velocity {choice} --scan {scan_text}", file=sys.stderr, flush=True)
            row = run_case(case, preset, refine_velocity=REFINE_VELOCITY[choice], scan=scan)
            with open(args.out, "a") as fh:
                fh.write(json.dumps(row) + "\n")
            errs = ", ".join(f"{k} {v:.3g}" for k, v in row.get("errors", {}).items())
            print(f"  -> {errs}; velocity {row.get('velocity_error', float('nan')):.3g} m/s off; {row.get('iterations')} "
                  f"iterations, {'converged' if row.get('converged') else 'NOT converged'}", file=sys.stderr, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

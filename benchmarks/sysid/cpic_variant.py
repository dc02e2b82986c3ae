"""One case of a sysid preset with some of CPIC's constants changed (issue 15, session 20).

    JAXMPM_CACHE_DIR=off PYTHONPATH=. python benchmarks/sysid/cpic_variant.py sand-bunny-0-tracks-cpic \\
        REFERENCE_TEMPERATURE=0.01 [COS_RAMP=0.001 PLANE_RAMP=0.001 ...]

Sets each ``NAME=VALUE`` on :mod:`jaxmpm.cpic` (module constants read when a step is traced),
runs the case in this process (truth regenerated with the changed physics, as the benchmark
does) and prints its errors, whether it converged, its iterations and its CPU seconds.
"""

from __future__ import annotations

import argparse
import time

import jaxmpm.cpic as cpic
from jaxmpm.bench_sysid import preset_cases, run_case


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("case")
    ap.add_argument("settings", nargs="*", help="NAME=VALUE for constants of jaxmpm.cpic")
    ap.add_argument("--preset", default="reduced")
    args = ap.parse_args(argv)
    for item in args.settings:
        name, value = item.split("=")
        if not hasattr(cpic, name):
            raise SystemExit(f"jaxmpm.cpic has no constant {name!r}")
        setattr(cpic, name, float(value))
    preset, cases = preset_cases(args.preset)
    case = next((c for c in cases if c.key == args.case), None)
    if case is None:
        raise SystemExit(f"no case {args.case!r} in preset {args.preset!r}")
    start = time.process_time()
    row = run_case(case, preset)
    errors = ", ".join(f"{k} {v:.3g}" for k, v in row["errors"].items())
    print(f"{args.case} {' '.join(args.settings)}: {errors}; converged {row['converged']}, "
          f"{row['iterations']} iterations, {time.process_time() - start:.0f} CPU s")


if __name__ == "__main__":
    main()

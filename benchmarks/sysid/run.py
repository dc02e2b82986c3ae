"""Run the system-identification benchmark (AS-DiffMPM's protocol regenerated with jaxmpm).

    python benchmarks/sysid/run.py --preset reduced --out bench_sysid
    jaxmpm bench sysid --preset reduced --out bench_sysid      # the same, once wired into the CLI

See docs/benchmark_sysid.md for the protocol and the measured table, and
``jaxmpm/bench_sysid.py`` for the implementation (``run_sysid_bench(argv) -> int``).
"""

import sys

from jaxmpm.bench_sysid import run_sysid_bench

__all__ = ["run_sysid_bench"]

if __name__ == "__main__":
    sys.exit(run_sysid_bench(sys.argv[1:]))

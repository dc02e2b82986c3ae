"""Step benchmark (the same as `jaxmpm bench step`): run from the repository root.

    python benchmarks/bench_step.py [--particles 25000] [--grid 64] [--steps 50] [--json out.json]

Times jaxmpm's forward step and forward+backward (through `--steps` checkpointed steps) for
several materials on the peers' cube (benchmarks/peers/common.py), and the Taichi and Warp
implementations of the same fixed-corotated step when they are installed
(`pip install -e ".[bench]"`). Each measurement runs in its own process (peak RSS).
"""

import sys

from jaxmpm.bench import bench_step

if __name__ == "__main__":
    sys.exit(bench_step(sys.argv[1:]))

import sys, numpy as np
sys.path.insert(0, "tests")
from collider_scenes import drop_spec, drop_run
import tempfile, pathlib
for flip in (0.0, 0.99):
    spec, tops = drop_spec(2, "sand", [("box", None, True), ("box", None, False)], pathlib.Path(tempfile.mkdtemp()))
    spec["flip"] = flip
    piles, _ = drop_run(spec, tops)
    for p in piles:
        print(flip, {k: (round(float(v), 4) if np.ndim(v) == 0 else None) for k, v in p.items()})

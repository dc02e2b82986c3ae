"""The 2D dam-break case study's base model (docs/case_studies/dam_break_2d.md) with APIC and
with a FLIP blend of 0.99 (session 54): RMS and mean error of the surge front against the
three measured columns. The front is the foremost particle's x, interpolated to the measured
times (the case study's probe reads the same particle with a cubic time interpolation)."""
import sys, pathlib, numpy as np
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2] / "examples"))
import dam_break_2d as case
from jaxmpm import load_scene, simulate_healthy

for name in ("mm_small", "mm_large", "ko"):
    t, x_meas, _, _ = case.load_front(name)
    row = [name]
    for flip in (0.0, 0.99):
        sc = load_scene({**case.scene_spec(name), "flip": flip})
        traj, ran, _ = simulate_healthy(sc.model, sc.params)
        front = np.asarray(traj.x)[:, :, 0].max(axis=1)
        pred = np.interp(t, np.asarray(traj.times), front)
        err = pred - x_meas
        row.append(f"flip {flip}: RMS {1e3*np.sqrt(np.mean(err**2)):.1f} mm, mean {1e3*err.mean():+.1f} mm "
                   f"({ran.substeps} substeps)")
    print(" | ".join(row), flush=True)

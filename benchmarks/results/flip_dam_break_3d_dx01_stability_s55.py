"""Session 55: the 3D dam break at dx = 0.1 m (stress-wave CFL 0.67 at 22 substeps) with a FLIP blend:
which runs the health check stops (CPIC box, grid-level box, no box; flip 0.9-0.99; 22 and 44 substeps)."""
import sys, time, pathlib, numpy as np
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2] / "examples"))
import dam_break_3d_obstacle as case
from jaxmpm import load_scene, simulate
for label, flip, n, mod in [("cpic", 0.99, 22, None), ("grid", 0.99, 22, "grid"), ("nobox", 0.99, 22, "nobox"),
                            ("cpic", 0.95, 22, None), ("cpic", 0.9, 22, None), ("cpic", 0.99, 44, None), ("cpic", 0.0, 22, None)]:
    spec = case.scene_spec(dx=0.1, t_end=1.0, flip=flip); spec["substeps"] = n
    if mod == "grid": spec["collision"] = "grid"
    if mod == "nobox": spec["colliders"] = spec["colliders"][:1]
    t0 = time.time(); sc = load_scene(spec); tr = simulate(sc.model, sc.params)
    print(label, flip, n, "first unstable frame", tr.first_unstable_frame(), "cfl max", float(np.nanmax(np.asarray(tr.cfl))), "wave", float(np.asarray(tr.wave_cfl)[0]), f"{time.time()-t0:.0f}s", flush=True)

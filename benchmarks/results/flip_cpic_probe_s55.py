"""flip + CPIC (session 55): an elastic block, sand and fluid dropped 4 cells on a CPIC box (dx = 5 cm),
2D and 3D, slip / sticky / friction, APIC and flip = 0.99 at 20 and 80 substeps. Usage: python flip_cpic_probe_s55.py [frames]"""
import sys, time, warnings, numpy as np

from jaxmpm import load_scene, simulate
warnings.simplefilter("ignore")
ELASTIC = {"model": "elastic", "E": 1e5, "nu": 0.3}
SAND = {"model": "sand", "friction_angle": 35.0, "E": 2e5}
FLUID = {"model": "newtonian", "mu": 1.0, "kappa": 1e4}
def scene(dim, mat, contact, fr, e, flip, substeps, frames, coll="cpic"):
    if dim == 2:
        return {"dim": 2, "dx": 0.05, "domain": {"lo": [0, 0], "hi": [1, 1]}, "frames": frames, "frame_dt": 0.01,
                "substeps": substeps, "collision": coll, "flip": flip,
                "bodies": [{"shape": "box", "lo": [0.4, 0.3], "hi": [0.6, 0.4], "material": mat}],
                "colliders": [{"type": "box", "lo": [0.0, 0.0], "hi": [1.0, 0.1], "contact": contact,
                               "friction": fr, "restitution": e}]}
    return {"dim": 3, "dx": 0.05, "domain": {"lo": [0, 0, 0], "hi": [1, 1, 1]}, "frames": frames, "frame_dt": 0.01,
            "substeps": substeps, "collision": coll, "flip": flip,
            "bodies": [{"shape": "box", "lo": [0.4, 0.3, 0.4], "hi": [0.6, 0.4, 0.6], "material": mat}],
            "colliders": [{"type": "box", "lo": [0.0, 0.0, 0.0], "hi": [1.0, 0.1, 1.0], "contact": contact,
                           "friction": fr, "restitution": e}]}
cases = [(2, "elastic", ELASTIC, "slip", 0, 0.5), (2, "elastic", ELASTIC, "sticky", 0, 0),
         (2, "elastic", ELASTIC, "friction", 0.3, 0), (2, "sand", SAND, "friction", 0.5, 0),
         (2, "fluid", FLUID, "slip", 0, 0), (3, "elastic", ELASTIC, "slip", 0, 0), (3, "sand", SAND, "friction", 0.5, 0)]
frames = int(sys.argv[1]) if len(sys.argv) > 1 else 100
for dim, name, mat, contact, fr, e in cases:
    for flip in (0.0, 0.99):
        for substeps in (20, 80):
            t0 = time.time()
            sc = load_scene(scene(dim, mat, contact, fr, e, flip, substeps, frames))
            tr = simulate(sc.model, sc.params)
            x = np.asarray(tr.x); nan = np.asarray(tr.nan)
            lowest = (np.nanmin(x[-1][:, 1]) - 0.1) / 0.05
            top = (np.nanmax(x[-1][:, 1]) - 0.1) / 0.05
            J = float(np.mean(np.linalg.det(np.asarray(tr.final.F)))) if name == "elastic" else float("nan")
            print(f"{dim}D {name:7s} {contact:8s} e={e} flip={flip} n={substeps}: nan@{int(np.argmax(nan)) if nan.any() else None} "
                  f"cfl {np.nanmax(np.asarray(tr.cfl)):.3f} gain {np.nanmax(np.asarray(tr.energy_gain)):.3f} "
                  f"lowest {lowest:.2f} top {top:.2f} cells meanJ {J:.3f} ({time.time()-t0:.0f}s)", flush=True)

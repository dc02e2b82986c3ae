"""Session 55: what the gauges read in the 3D dam break at dx = 0.05 m, APIC against flip = 0.99,
at the substep counts given (default 88). The case study's gauge reads the highest particle within a cell of it (spray
counts); beside it, the depth the column's particles would fill (their volume over the column's
area). Per gauge: the held-out RMS error of both readings against the 1 kHz record, and at H1
(behind the box) the readings over time at the first count.
Usage: python flip_dam_break_3d_h1_s55.py [88,176,352]"""
import sys, pathlib, time
import numpy as np
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2] / "examples"))
import dam_break_3d_obstacle as case
from jaxmpm import load_scene, simulate

dx, t_end = 0.05, 1.0
t_obs, h_obs = case.load_gauges(t_end, every=1)
held = float(np.quantile(np.unique(case.load_gauges(t_end)[0]), 0.7))
late = t_obs >= held
counts = [int(n) for n in (sys.argv[1] if len(sys.argv) > 1 else "88").split(",")]
for flip, substeps in [(f, n) for n in counts for f in (0.0, 0.99)]:
    t0 = time.time()
    spec = case.scene_spec(dx=dx, t_end=t_end, flip=flip)
    spec["substeps"] = substeps
    sc = load_scene(spec)
    tr = simulate(sc.model, sc.params)
    x = np.asarray(tr.x)
    tt = np.arange(x.shape[0]) * sc.model.frame_dt
    vol = np.concatenate([np.asarray(b.vol0) for b in sc.model.bodies])
    print(f"flip = {flip}, {substeps} substeps: {time.time() - t0:.0f} s; NaN {bool(np.asarray(tr.nan).any())}, "
          f"energy gain max {float(np.asarray(tr.energy_gain).max()):.3f}")
    readings = {}
    for j, (g, xg) in enumerate(case.GAUGES.items()):
        top, depth, count = [], [], []
        for f in range(x.shape[0]):
            near = (np.abs(x[f, :, 0] - xg) <= dx) & (np.abs(x[f, :, 2] - 0.5) <= dx)
            top.append(x[f, near, 1].max() + dx / 4 if near.any() else 0.0)
            depth.append(vol[near].sum() / (2 * dx * dx))  # z in [0.45, 0.5]: the simulated half of the column
            count.append(int(near.sum()))
        readings[g] = (np.array(top), np.array(depth), np.array(count))
        rms = [float(np.sqrt(np.mean((np.interp(t_obs, tt, r, left=r[0])[late] - h_obs[j][late]) ** 2)))
               for r in readings[g][:2]]
        print(f"  {g}: held-out RMS, gauge (highest particle) {rms[0]:.3f} m, column depth {rms[1]:.3f} m")
    if substeps != counts[0]:
        continue
    top, depth, count = readings["H1"]
    print("  H1 | t (s) | gauge (m) | column depth (m) | particles | measured (m)")
    for f in range(30, x.shape[0], 2):
        print(f"     | {tt[f]:.2f} | {top[f]:.3f} | {depth[f]:.3f} | {count[f]} | {np.interp(tt[f], t_obs, h_obs[0]):.3f}")

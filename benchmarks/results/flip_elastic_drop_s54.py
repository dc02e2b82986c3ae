import sys, numpy as np
sys.path.insert(0, "tests")
from test_collision_modes import _one_collider_scene
from jaxmpm import load_scene, simulate
COLL, KIND = sys.argv[1], sys.argv[2]
for flip in (0.95, 0.99):
  for substeps in (20, 80):
    spec = _one_collider_scene(COLL, KIND, "slip", 0.0, 0.0)
    spec.update(frames=60, substeps=substeps, flip=flip)
    sc = load_scene(spec)
    tr = simulate(sc.model, sc.params)
    y = np.asarray(tr.x)[..., 1]
    nan = np.asarray(tr.nan)
    print(flip, substeps, "nan at frame", int(np.argmax(nan)) if nan.any() else None, "cfl max", float(np.nanmax(np.asarray(tr.cfl))), "wave", float(np.asarray(tr.wave_cfl)[0]), "lowest", float(np.nanmin(y) - 0.1) / 0.05)

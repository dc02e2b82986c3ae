"""The measured data shipped for the discrepancy case studies load with their units and SOURCE notes."""

import importlib.util
import math
from pathlib import Path

import numpy as np

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _module(name):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_martin_moyce_fronts_and_scene():
    db = _module("dam_break_2d")
    assert (db.DATA / "SOURCE.md").is_file()
    for name, (_, a, _) in db.SERIES.items():
        t, x, T, Z = db.load_front(name)
        assert np.all(np.diff(t) > 0) and np.all(t > 0) and np.all(Z >= 1.0)
        np.testing.assert_allclose(t * math.sqrt(2 * 9.81 / a), T)  # T = t sqrt(2 g / a) for n^2 = 2
        np.testing.assert_allclose(x, Z * a)
        assert t[-1] < 0.6  # seconds, not dimensionless time
    # Froude similarity fails in the data: the small column lags the large one at the same T
    _, _, T1, Z1 = db.load_front("mm_small")
    _, _, T2, Z2 = db.load_front("mm_large")
    assert np.interp(5.0, T1, Z1) < 0.95 * np.interp(5.0, T2, Z2)
    spec = db.scene_spec("mm_large", cells=6)
    assert spec["bodies"][0]["hi"] == [db.SERIES["mm_large"][1], 2 * db.SERIES["mm_large"][1]]
    assert spec["colliders"][0]["contact"] == "slip"
    obs = db.observation("mm_large")
    assert obs.probe_names == ("front_x",) and obs.probe_values.shape == obs.probe_times.shape
    # measured, so not the model's own data: fit's and discover's notes on the transfers apply
    from jaxmpm.scene import load_scene

    assert obs.scene is None and not obs.made_by(load_scene(spec).model)


def test_spheric_gauges():
    db = _module("dam_break_3d_obstacle")
    assert (db.DATA / "SOURCE.md").is_file()
    t, h = db.load_gauges(1.2, every=1)
    assert h.shape == (4, len(t)) and abs(t[1] - t[0] - 0.001) < 1e-4
    # corrected labels: H3 (x = 1.488) is wetted first, H1 (in the lee of the box) last
    arrival = {k: t[np.argmax(h[i] > 0.005)] for i, k in enumerate(db.GAUGES) if k != "H4"}
    assert abs(arrival["H3"] - 0.19) < 0.02 and abs(arrival["H2"] - 0.354) < 0.02 and abs(arrival["H1"] - 0.912) < 0.02
    assert abs(h[3, 0] - 0.547) < 0.002  # H4 starts in the reservoir, 0.55 m deep

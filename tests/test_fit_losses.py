"""Loss terms (tracks, probes, images), the objective's checks, and bad input to fits."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import block_spec

from jaxmpm.errors import JaxmpmError, ObservationError
from jaxmpm.cli import parse_weights
from jaxmpm.fit import FitConfig, fit, fit_scene
from jaxmpm.observe import check_scene_compatible
from jaxmpm.identify.residuals import (
    build_objective,
    chamfer_residuals,
    depth_gauge,
    gauge,
    probe_function,
    register_probe,
)
from jaxmpm.model import initial_state
from jaxmpm.observe import Observation
from jaxmpm.scene import load_scene
from jaxmpm.step import simulate

FLOOR = {"point": [0.0, 0.1], "normal": [0.0, 1.0], "contact": "sticky"}


def _scene(mu=50.0, **kw):
    kw.setdefault("frames", 5)
    kw.setdefault("substeps", 20)
    return load_scene(block_spec(2, {"model": "newtonian", "mu": mu, "kappa": 1e4}, dx=0.05, lo=[0.3, 0.12],
                                 hi=[0.5, 0.3], floor=FLOOR, **kw))


@pytest.fixture(scope="module")
def truth():
    scene = _scene()
    traj = jax.jit(lambda p: simulate(scene.model, p))(scene.params)
    return scene, traj


# --------------------------------------------------------------------------- probes


def test_builtin_probes_measure_the_state(truth):
    scene, _ = truth
    state = initial_state(scene.model, scene.params)
    h = 0.05 / 2  # 4 particles per cell in 2D
    x = np.asarray(state.x)
    assert float(probe_function("front_x")(state, scene.model)) == pytest.approx(x[:, 0].max() + h / 2, rel=1e-6)
    assert float(probe_function("back_x")(state, scene.model)) == pytest.approx(x[:, 0].min() - h / 2, rel=1e-6)
    assert float(probe_function("height")(state, scene.model)) == pytest.approx(x[:, 1].max() + h / 2, rel=1e-6)
    assert float(probe_function("centroid_y")(state, scene.model)) == pytest.approx(x[:, 1].mean(), rel=1e-6)
    # a gauge inside the block reads its top, one outside reads 0 (dry)
    assert float(probe_function("gauge@0.4")(state, scene.model)) == pytest.approx(x[:, 1].max() + h / 2, rel=1e-6)
    assert float(gauge(0.8)(state, scene.model)) == 0.0


@pytest.mark.parametrize("dim", [2, 3])
def test_a_depth_gauge_reads_the_depth_of_the_column_and_not_its_spray(dim):
    """``depth_gauge`` / ``depth@X[,Z]``: on a resting lattice it reads the block's depth
    (0.2 m, 8 particle layers); 0 where dry; on the domain's face (a
    symmetry plane) the whole column's depth, not half; in 3D without z, a line gauge (depth
    times the block's share of the width). One particle 0.4 m above the column lifts
    ``gauge`` to it and ``depth`` by its own volume only (V0 / dx^(D-1) at most)."""
    scene = load_scene(block_spec(dim, dx=0.05, lo=[0.3, 0.1, 0.3][:dim], hi=[0.5, 0.3, 1.0][:dim]))
    state = initial_state(scene.model, scene.params)
    at = [0.4] if dim == 2 else [0.4, 0.6]
    name = "depth@" + ",".join(map(str, at))
    read = lambda probe, s=state: float(probe(s, scene.model))  # noqa: E731
    assert read(probe_function(name)) == pytest.approx(0.2, rel=1e-5)
    assert read(depth_gauge(0.8, *at[1:])) == 0.0
    if dim == 3:
        assert read(depth_gauge(0.4, 1.0)) == pytest.approx(0.2, rel=1e-5)  # on the domain's face
        assert read(depth_gauge(0.4)) == pytest.approx(0.2 * 0.7, rel=1e-5)  # across the width
    # a spray particle above the gauge
    v0 = float(state.vol0[0])
    spray = state.x[0].at[0].set(0.4).at[1].set(0.7)
    if dim == 3:
        spray = spray.at[2].set(0.6)
    wet = _with_one_more(state, jnp.concatenate([state.x, spray[None]]), v0)
    assert read(gauge(*at), wet) == pytest.approx(0.7 + 0.25 * 0.05, rel=1e-5)
    added = read(depth_gauge(*at), wet) - read(depth_gauge(*at))
    assert 0.0 < added <= v0 / 0.05 ** (dim - 1) * 1.0001


def test_probe_series_reads_a_probe_at_every_recorded_frame():
    """``probe_series``: a probe at each frame of a trajectory, the same as the probe applied
    to that frame's state (the first frame: the initial state; the last: the final one). A
    block in free fall: its top is lower at every frame."""
    from jaxmpm.identify import probe_series

    scene = load_scene(block_spec(2, frames=4, substeps=10))
    traj = simulate(scene.model, scene.params)
    fn = probe_function("top_y")
    series = probe_series(fn, scene.model, traj)
    assert series.shape == (4,)
    assert series[0] == pytest.approx(float(fn(initial_state(scene.model, scene.params), scene.model)), rel=1e-6)
    assert series[-1] == pytest.approx(float(fn(traj.final, scene.model)), rel=1e-6)
    assert np.all(np.diff(series) < 0), series


def _with_one_more(state, x, v0):
    """``state`` with positions ``x`` (one particle more, of volume ``v0``)."""
    from jaxmpm.state import make_state

    n = x.shape[0]
    return make_state(x, jnp.zeros_like(x), jnp.full(n, 1000.0 * v0), jnp.full(n, v0))


def test_a_depth_gauge_has_the_gradient_of_its_finite_differences(truth):
    """The depth reading is continuous in the positions (a tent kernel): its derivative along
    a random displacement of all particles matches central differences."""
    scene, traj = truth
    from jaxmpm.state import make_state

    x = traj.x[-1]
    state = make_state(x, traj.v[-1], traj.final.mass, traj.final.vol0)
    probe = depth_gauge(0.41)
    direction = jax.random.normal(jax.random.PRNGKey(0), x.shape) * 1e-3
    of = lambda t: probe(make_state(x + t * direction, state.v, state.mass, state.vol0), scene.model)  # noqa: E731
    slope = float(jax.grad(of)(0.0))
    fd = (float(of(1e-2)) - float(of(-1e-2))) / 2e-2
    assert abs(slope) > 1e-4
    assert slope == pytest.approx(fd, rel=2e-2)


def test_probe_registry_and_unknown_names(truth):
    scene, _ = truth
    register_probe("gauge_test_H1", gauge(0.4))
    state = initial_state(scene.model, scene.params)
    assert float(probe_function("gauge_test_H1")(state, scene.model)) > 0.2
    with pytest.raises(ObservationError, match="unknown probe 'gauge_H9'.*register_probe"):
        probe_function("gauge_H9")
    with pytest.raises(JaxmpmError, match="non-empty"):
        register_probe("", gauge(0.1))


def test_fit_mu_from_a_front_position_probe(truth):
    """A dam-break-like identification from the front position time series alone."""
    scene, _ = truth
    traj = jax.jit(lambda p: simulate(scene.model, p, observe=lambda s: probe_function("front_x")(s, scene.model)))(
        scene.params)
    obs = Observation(times=np.asarray(traj.times), probe_names=("front_x",),
                      probe_times=np.asarray(traj.times)[None], probe_values=np.asarray(traj.extra)[None])
    start = _scene(mu=10.0)
    result = fit(start.model, start.params, obs, ["mu"], FitConfig(stages=None))
    assert result.converged, result.message
    assert abs(np.log10(float(result.values["mu"])) - np.log10(50.0)) < 0.02
    assert result.stages[0]["terms"] == {"probes": 1.0}


# --------------------------------------------------------------------------- tracks


@pytest.mark.parametrize("point_ids", ["particles", None], ids=["by-id", "chamfer"])
def test_a_tracks_window_is_the_observation_cut_to_it(truth, point_ids):
    scene, traj = truth
    start = _scene(mu=10.0)
    times, x = np.asarray(traj.times), np.asarray(traj.x)
    whole = build_objective(start.model, Observation(times=times, positions=x, point_ids=point_ids))
    window = build_objective(start.model, Observation(times=times, positions=x, point_ids=point_ids), until=times[2])
    cut = build_objective(start.model, Observation(times=times[:3], positions=x[:3], point_ids=point_ids))
    assert window.frames == cut.frames == 3 and window.count == cut.count
    assert window.residuals(start.params).shape == whole.residuals(start.params).shape
    np.testing.assert_allclose(float(window.loss(start.params)), float(cut.loss(start.params)), rtol=1e-5)
    assert float(window.loss(start.params)) < float(whole.loss(start.params))


def test_chamfer_matches_brute_force():
    rng = np.random.default_rng(0)
    sim = rng.normal(size=(37, 3))
    obs = rng.normal(size=(2100, 3))  # more than one chunk
    valid = rng.uniform(size=2100) > 0.2
    r = np.asarray(chamfer_residuals(jnp.asarray(sim), jnp.asarray(obs), jnp.asarray(valid)))
    d = np.linalg.norm(obs[:, None] - sim[None], axis=-1)
    want = np.concatenate([np.where(valid, d.min(1), 0.0), d[valid].min(0)])
    np.testing.assert_allclose(r, want, rtol=1e-5, atol=1e-5)


def test_track_residuals_are_zero_at_the_truth_and_scaled(truth):
    scene, traj = truth
    obs = Observation(times=np.asarray(traj.times), positions=np.asarray(traj.x), point_ids="particles")
    objective = build_objective(scene.model, obs)
    assert objective.terms == {"tracks": 1.0}
    r = jax.jit(objective.residuals)(scene.params)
    assert float(jnp.max(jnp.abs(r))) < 1e-6
    T, N, D = np.shape(traj.x)
    assert r.shape == (T * N * D,) and objective.count == T * N * D
    # the scale makes sum(r^2) the mean squared error per point (m^2): a 1 cm offset -> 1e-4
    shifted = Observation(times=obs.times, positions=obs.positions + np.array([0.01, 0.0]), point_ids="particles")
    assert build_objective(scene.model, shifted).term_losses(scene.params)["tracks"] == pytest.approx(1e-4, rel=1e-3)
    # Chamfer (points that are not particles): also zero at the truth
    chamfer = build_objective(scene.model, Observation(times=obs.times[:3], positions=obs.positions[:3]))
    assert float(jnp.max(jax.jit(chamfer.residuals)(scene.params))) < 1e-5


# --------------------------------------------------------------------------- bad input


def test_bad_observations_are_clear_errors(truth):
    scene, traj = truth
    times = np.asarray(traj.times)
    with pytest.raises(ObservationError, match="too few observed frames"):
        build_objective(scene.model, Observation(times=times[:1], positions=np.asarray(traj.x)[:1],
                                                 point_ids="particles"))
    with pytest.raises(ObservationError, match="all NaN"):
        Observation(times=times, positions=np.full(np.shape(traj.x), np.nan))
    partial = np.asarray(traj.x).copy()
    partial[:3] = np.nan  # NaN in the whole window t <= 2 frames
    with pytest.raises(ObservationError, match="all NaN in the fitted time window"):
        build_objective(scene.model, Observation(times=times, positions=partial, point_ids="particles"), until=times[2])
    obs = Observation(times=times, positions=np.asarray(traj.x), point_ids="particles")
    with pytest.raises(ObservationError, match="'silhouette' has weight.*no data"):
        build_objective(scene.model, obs, weights={"silhouette": 1.0})
    with pytest.raises(JaxmpmError, match="unknown loss term 'colour'"):
        build_objective(scene.model, obs, weights={"colour": 1.0})
    with pytest.raises(ObservationError, match="no loss term has a positive weight"):
        build_objective(scene.model, obs, weights={"tracks": 0.0})
    with pytest.raises(JaxmpmError, match="unknown parameter 'E'.*newtonian"):
        fit(scene.model, scene.params, obs, ["E"])
    with pytest.raises(JaxmpmError, match="unknown fit method 'sgd'"):
        fit(scene.model, scene.params, obs, ["mu"], FitConfig(method="sgd"))


def test_masks_of_the_wrong_size_are_rejected():
    scene = load_scene(block_spec(3, dx=0.1, frames=3, substeps=10))
    K = np.array([[40.0, 0, 32], [0, 40.0, 32], [0, 0, 1]])[None]
    c2w = np.eye(4)[None]
    c2w[0, :3, 3] = [0.5, 0.4, -1.0]
    masks = np.zeros((1, 3, 16, 16), np.uint8)  # the intrinsics were made for 64x64 images
    obs = Observation(times=np.array([0.0, 0.04, 0.08]), masks=masks, intrinsics=K, cam_to_world=c2w)
    with pytest.raises(ObservationError, match="principal point.*16x16.*64x64"):
        build_objective(scene.model, obs)
    images = np.zeros((1, 3, 8, 8, 3), np.uint8)
    with pytest.raises(ObservationError, match="disagree"):
        build_objective(scene.model, Observation(times=obs.times, masks=np.zeros((1, 3, 64, 64), np.uint8),
                                                 images=images, intrinsics=K, cam_to_world=c2w))


def test_observation_of_another_scene_is_rejected(truth):
    scene, traj = truth
    other = load_scene(block_spec(2, {"model": "newtonian", "mu": 50.0, "kappa": 1e4}, dx=0.05, lo=[0.3, 0.12],
                                  hi=[0.55, 0.3], floor=FLOOR, frames=5, substeps=20))
    obs = Observation(times=np.asarray(traj.times), positions=np.asarray(traj.x), point_ids="particles",
                      scene=other.to_json())
    with pytest.raises(ObservationError, match=r"different scene.*bodies\[0\]\.hi"):
        fit_scene(scene, obs, ["mu"])
    # material values, velocity and substeps may differ
    spec = dict(scene.spec, substeps=40)
    spec["bodies"] = [dict(scene.spec["bodies"][0], material={"model": "newtonian", "mu": 1.0, "kappa": 1e3})]
    check_scene_compatible(spec, scene.spec)
    spec["bodies"] = [dict(scene.spec["bodies"][0], material={"model": "elastic", "E": 1e5, "nu": 0.3})]
    with pytest.raises(ObservationError, match="material.model"):
        check_scene_compatible(spec, scene.spec)


def test_parse_weights():
    assert parse_weights("tracks=1, silhouette=0.5") == {"tracks": 1.0, "silhouette": 0.5}
    assert parse_weights(None) is None
    with pytest.raises(JaxmpmError, match="name=number"):
        parse_weights("tracks")

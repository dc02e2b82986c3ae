"""Image terms: silhouettes and masked RGB through the renderers, on a coarse 3D scene."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiles import counting_compilations
from scenes import block_spec

from jaxmpm.fit import FitConfig, fit
from jaxmpm.identify.residuals import build_objective, make_fit_renderer, particle_colors
from jaxmpm.observe import Observation
from jaxmpm.render import pacnerf_rig, render_views
from jaxmpm.scene import load_scene
from jaxmpm.step import simulate

FLOOR = {"point": [0, 0.1, 0], "normal": [0, 1, 0], "contact": "sticky"}


def _spec(mu):
    return block_spec(3, {"model": "newtonian", "mu": mu, "kappa": 1e4}, dx=0.1, lo=[0.35, 0.2, 0.35],
                      hi=[0.65, 0.4, 0.65], frames=4, substeps=15, velocity=[0.5, -1.0, 0.0], floor=FLOOR)


@pytest.fixture(scope="module")
def observed():
    scene = load_scene(_spec(200.0))
    traj = jax.jit(lambda p: simulate(scene.model, p))(scene.params)
    cams = pacnerf_rig(3, radius=2.0, target=(0.5, 0.25, 0.5), fov_deg=40.0, res=24)
    # observe with the renderer the fit uses (a domain-wide grid at the particle spacing)
    rendered = render_views(np.asarray(traj.x), cams, make_fit_renderer("volume", scene.model))
    return Observation(times=np.asarray(traj.times), masks=rendered["masks"], images=rendered["images"],
                       intrinsics=rendered["intrinsics"], cam_to_world=rendered["cam_to_world"])


def test_silhouette_and_rgb_objectives(observed):
    truth, start = load_scene(_spec(200.0)), load_scene(_spec(5.0))
    objective = build_objective(truth.model, observed, weights={"silhouette": 1.0, "rgb": 1.0}, num_pixels=48)
    assert objective.terms == {"silhouette": 1.0, "rgb": 1.0}
    loss = jax.jit(objective.loss)
    assert float(loss(truth.params)) < 0.5 * float(loss(start.params))
    assert float(loss(start.params)) == float(loss(start.params))  # the fixed pixel batch is deterministic


def _first(obs: Observation, k: int) -> Observation:
    """The observation cut to its first ``k`` times."""
    return Observation(times=obs.times[:k], masks=obs.masks[:, :k], images=obs.images[:, :k],
                       intrinsics=obs.intrinsics, cam_to_world=obs.cam_to_world)


def test_a_window_is_the_observation_cut_to_it_and_shares_one_compilation(observed):
    """An objective over a window (``until``) gives the loss of the observation cut to that
    window (same pixels, same scales: only its frames are simulated and rendered), has the
    same residual length as the whole observation's, and a stage's compiled
    residual-and-Jacobian program serves every window without compiling again."""
    import jax.monitoring

    from jaxmpm.fit import StageResiduals
    from jaxmpm.identify.parameters import to_unconstrained
    from jaxmpm.identify.solvers import residuals_and_jacobian

    scene = load_scene(_spec(50.0))
    options = dict(weights={"silhouette": 1.0, "rgb": 0.5}, num_pixels=48)
    whole = build_objective(scene.model, observed, **options)
    k = 2
    window = build_objective(scene.model, observed, until=float(observed.times[k - 1]), **options)
    cut = build_objective(scene.model, _first(observed, k), **options)
    assert window.frames == cut.frames == k and window.length == whole.length == len(observed.times)
    assert window.count == cut.count and window.residuals(scene.params).shape == whole.residuals(scene.params).shape
    np.testing.assert_allclose(float(window.loss(scene.params)), float(cut.loss(scene.params)), rtol=1e-5)

    y = {"mu": to_unconstrained("mu", jnp.asarray(50.0))}
    losses = []
    with counting_compilations() as compiles:
        for until in (float(observed.times[1]), None):
            objective = build_objective(scene.model, observed, until=until, **options)
            rj, flat, _ = residuals_and_jacobian(StageResiduals(objective.program, scene.params, ("mu",)), y)
            r, J = rj(flat)
            losses.append(float(jnp.sum(r**2)))
            if until is not None:
                compiled = len(compiles)
    assert compiled > 0 and len(compiles) == compiled  # the second window compiled nothing
    assert losses[1] > losses[0] > 0  # ... and is not the first window again


def test_random_pixel_batches():
    """Adam's batches: n per view and frame, mostly from each view's candidate region."""
    from jaxmpm.identify.residuals import _random_pixels

    table = jnp.asarray([[5, 6, 7, 7], [1, 2, 3, 4]], jnp.int32)  # view 0 has 3 candidates (padded)
    count = jnp.asarray([3, 4], jnp.int32)
    a = np.asarray(_random_pixels(jax.random.PRNGKey(1), table, count, 2, 2, 100, 40, 10))
    b = np.asarray(_random_pixels(jax.random.PRNGKey(2), table, count, 2, 2, 100, 40, 10))
    assert a.shape == (2, 2, 40) and not np.array_equal(a, b)
    assert set(a[:, 0, :30].ravel()) <= {5, 6, 7} and set(a[:, 1, :30].ravel()) <= {1, 2, 3, 4}
    assert a.min() >= 0 and a.max() < 100


def test_particle_colours_from_images(observed):
    scene = load_scene(_spec(200.0))
    colors = particle_colors(scene.model, observed)
    assert colors.shape == (scene.model.num_particles, 3)
    # the renderer's default orange, washed towards the white background at soft edges
    assert np.all(colors[:, 0] > colors[:, 2])


def test_fit_mu_from_silhouettes(observed):
    """Levenberg–Marquardt through the renderer (forward-mode Jacobian of the silhouettes)."""
    start = load_scene(_spec(20.0))
    result = fit(start.model, start.params, observed, ["mu"], FitConfig(stages=None, num_pixels=64, max_steps=30))
    assert result.stages[0]["terms"] == {"silhouette": 1.0}
    assert result.converged, result.message
    assert abs(np.log10(float(result.values["mu"]) / 200.0)) < 0.05, float(result.values["mu"])
    assert np.isfinite(result.std["mu"]) and result.std["mu"] > 0


def test_the_velocity_stage_can_start_from_the_silhouettes_free_fall():
    """``free_fall_velocity``: a block thrown at (0.5, -1, 0) m/s, falling freely in view of
    four cameras, gives its velocity from the masks alone (of the guess only gravity is used)
    to a starting point's accuracy: 0.07 m/s off measured (a box's silhouette centroids are
    not its projected centre), against 1.12 for a guess of rest; ``better_start`` takes a
    candidate only where it lowers the loss."""
    from jaxmpm.fit import better_start, free_fall_velocity

    box = dict(dx=0.05, lo=[0.35, 0.5, 0.35], hi=[0.65, 0.7, 0.65], frames=4, substeps=15)
    truth = load_scene(block_spec(3, velocity=[0.5, -1.0, 0.0], **box))
    traj = jax.jit(lambda p: simulate(truth.model, p))(truth.params)
    cams = pacnerf_rig(4, radius=2.0, target=(0.5, 0.5, 0.5), fov_deg=40.0, res=64)
    rendered = render_views(np.asarray(traj.x), cams, make_fit_renderer("volume", truth.model))
    obs = Observation(times=np.asarray(traj.times), masks=rendered["masks"], intrinsics=rendered["intrinsics"],
                      cam_to_world=rendered["cam_to_world"])
    guess = load_scene(block_spec(3, **box))
    v = free_fall_velocity(guess.model, guess.params, obs)
    assert np.linalg.norm(v - np.array([0.5, -1.0, 0.0])) < 0.1, v
    # from untracked points: their centre's free flight, undone exactly (the simulator's own)
    points = Observation(times=obs.times, positions=np.asarray(traj.x)[:, ::3])
    np.testing.assert_allclose(free_fall_velocity(guess.model, guess.params, points), [0.5, -1.0, 0.0], atol=1e-4)
    tracked = Observation(times=obs.times, positions=np.asarray(traj.x), point_ids="particles")
    assert free_fall_velocity(guess.model, guess.params, tracked) is None  # (tracks pin the velocity themselves)

    def residuals(y):
        return jnp.stack([y["v"][0] - 1.0, y["v"][1] + 2.0])

    y0 = {"v": jnp.zeros(2)}
    better, record = better_start(residuals, y0, {"v": jnp.asarray([0.9, -1.8])})
    assert record["taken"] and record["candidate_loss"] < record["start_loss"] == pytest.approx(5.0)
    np.testing.assert_array_equal(better["v"], jnp.asarray([0.9, -1.8]))
    kept, record = better_start(residuals, y0, {"v": jnp.asarray([4.0, 4.0])})
    assert not record["taken"] and kept["v"] is y0["v"]

"""Identification from tracks: each material's parameters from PAC-NeRF's initial guesses."""

import jax.numpy as jnp
import numpy as np
import pytest
from scenes import MATERIAL_CASES, block_spec

from jaxmpm.constitutive import MATERIALS
from jaxmpm.errors import JaxmpmError, ObservationError
from jaxmpm.fit import SCAN_DECADES, FitConfig, fit
from jaxmpm.identify import LOG10_PARAMS, from_unconstrained, resolve_name, to_unconstrained
from jaxmpm.observe import Observation
from jaxmpm.scene import load_scene
from jaxmpm.step import simulate

FLOOR = {"point": [0.0, 0.1], "normal": [0.0, 1.0], "contact": "sticky"}
#: per material: frames, substeps (CFL-safe for the truth and the initial guess)
SETTINGS = {"newtonian": (8, 60), "viscoplastic": (8, 120), "elastic": (8, 80), "plasticine": (8, 80), "sand": (8, 260)}


def _spec(material, model):
    frames, substeps = SETTINGS[model]
    return block_spec(2, material, dx=0.04, lo=[0.4, 0.12], hi=[0.6, 0.32], frames=frames, substeps=substeps,
                      velocity=[0.5, -2.0], floor=FLOOR)


@pytest.mark.parametrize("model", list(MATERIAL_CASES))
def test_fit_recovers_parameters_from_tracks(model):
    truth, guess = MATERIAL_CASES[model]
    names = list(MATERIALS[model].required())
    true_scene = load_scene(_spec(truth, model))
    traj = simulate(true_scene.model, true_scene.params)
    obs = Observation(times=np.asarray(traj.times), positions=np.asarray(traj.x), point_ids="particles")
    start = load_scene(_spec({"model": model, **guess}, model))
    result = fit(start.model, start.params, obs, names, FitConfig(max_steps=60, stages=None))
    assert result.loss[-1] < 1e-3 * result.loss[0]
    for name in names:
        est = float(result.values[name])
        if name in LOG10_PARAMS:
            assert abs(np.log10(est) - np.log10(truth[name])) < 0.02, (name, est, truth[name])
        elif name == "friction_angle":
            assert abs(est - truth[name]) < 0.5, (name, est)
        else:
            assert abs(est - truth[name]) < 0.01, (name, est)
        assert np.isfinite(result.std[name])
    assert result.converged, result.message


@pytest.mark.x64
@pytest.mark.parametrize("name,value", [("E", 3e5), ("mu", 0.2), ("nu", 0.3), ("nu", -0.3), ("friction_angle", 35.0)])
def test_parameter_spaces_round_trip(name, value):
    y = to_unconstrained(name, jnp.asarray(value, jnp.float64))
    np.testing.assert_allclose(from_unconstrained(name, y), value, rtol=1e-12)
    if name in LOG10_PARAMS:
        np.testing.assert_allclose(y, np.log10(value))


def test_parameter_names_are_resolved_or_rejected():
    scene = load_scene(_spec(MATERIAL_CASES["newtonian"][0], "newtonian"))
    assert resolve_name(scene.model, scene.params, "mu") == ("bodies", 0, "mu")
    assert resolve_name(scene.model, scene.params, "body0.kappa") == ("bodies", 0, "kappa")
    assert resolve_name(scene.model, scene.params, "floor.friction") == ("colliders", 0, "friction")
    with pytest.raises(JaxmpmError, match="unknown parameter 'E'"):
        resolve_name(scene.model, scene.params, "E")
    with pytest.raises(JaxmpmError, match="no body or collider named 'wall'"):
        resolve_name(scene.model, scene.params, "wall.friction")


def test_fit_rejects_mismatched_tracks():
    scene = load_scene(_spec(MATERIAL_CASES["newtonian"][0], "newtonian"))
    bad = Observation(times=np.array([0.0, 0.04]), positions=np.zeros((2, 7, 2)), point_ids="particles")
    with pytest.raises(ObservationError, match="7 points"):
        fit(scene.model, scene.params, bad, ["mu"])


def _plateau(y):
    """Residuals of one log10 variable whose loss is flat far from its minimum at y = 2.3 and
    NaN at y >= 3.9."""
    mu = y["mu"]
    return jnp.where(mu >= 3.9, jnp.nan, jnp.sqrt(jnp.tanh((mu - 2.3) ** 2)) + 0.0 * y["v"])[None]


def test_scan_start_keeps_the_lowest_loss_and_skips_unhealthy_points():
    from jaxmpm.fit import scan_start

    y0 = {"mu": jnp.asarray(1.0), "v": jnp.asarray(0.5)}
    y, rec = scan_start(_plateau, y0, ["mu"], (-1.0, 1.0, 2.0, 3.0))
    assert float(y["mu"]) == pytest.approx(2.0) and float(y["v"]) == 0.5  # 10^2 beats 10^3 (0.09 vs 0.49 after tanh)
    assert rec["moved"] == {"mu": 1.0} and rec["points"] == 5
    assert rec["best_loss"] == pytest.approx(np.tanh(0.09), rel=1e-5) and rec["start_loss"] == pytest.approx(np.tanh(1.69), rel=1e-5)
    # an unhealthy point (+3 decades: NaN) is never taken, and an unhealthy start is left for any healthy point
    y, rec = scan_start(_plateau, {"mu": jnp.asarray(1.0), "v": jnp.asarray(0.0)}, ["mu"], (3.0,))
    assert float(y["mu"]) == 1.0 and rec["moved"] == {}
    y, rec = scan_start(_plateau, {"mu": jnp.asarray(4.0), "v": jnp.asarray(0.0)}, ["mu"], (-1.0, -2.0))
    assert float(y["mu"]) == pytest.approx(2.0) and rec["moved"] == {"mu": -2.0} and rec["start_loss"] == np.inf


def test_coordinate_search_moves_one_component_of_a_vector_at_a_time():
    from jaxmpm.fit import coordinate_search

    def loss(y):  # minimum at v = (0.3, -1.0), flat in mu; NaN where v[1] > 0
        v = y["v"]
        return jnp.where(v[1] > 0, jnp.nan, (v[0] - 0.3) ** 2 + 4 * (v[1] + 1.0) ** 2 + 0 * y["mu"])

    y0 = {"v": jnp.asarray([0.0, -1.2]), "mu": jnp.asarray(2.0)}
    y, rec = coordinate_search(loss, y0, [("v", 0), ("v", 1)], (-0.3, 0.3, 1.5))
    np.testing.assert_allclose(np.asarray(y["v"]), [0.3, -1.2 + 0.3], atol=1e-6)  # +1.5 on v[1]: NaN, not taken
    assert rec["moved"] == {"v[0]": 0.3, "v[1]": 0.3} and rec["points"] == 7 and float(y["mu"]) == 2.0
    assert rec["best_loss"] == pytest.approx(4 * 0.1**2, rel=1e-4) and rec["start_loss"] == pytest.approx(0.09 + 0.16)


def test_a_velocity_stage_that_stops_short_is_polished_and_solved_again(monkeypatch):
    """Where the last stage fitting the velocity stops without converging and the data track no
    particle, each velocity component is moved by ± VELOCITY_POLISH × dx / T and the stage is
    solved again from a lower loss. Here the solver's first run is made to stop at its start,
    the velocity 0.05 dx / T off in x: the polish finds exactly that move, and the second run
    converges to the truth. Not from tracks of every particle, nor with polish=()."""
    import importlib

    from jaxmpm.fit import VELOCITY_POLISH
    from jaxmpm.identify.solvers import SolverOutcome

    fit_module = importlib.import_module("jaxmpm.fit")
    truth, _ = MATERIAL_CASES["newtonian"]
    true_scene = load_scene(_spec(truth, "newtonian"))
    traj = simulate(true_scene.model, true_scene.params)
    times = np.asarray(traj.times)
    unit = 0.04 / float(times[-1])  # dx / T
    off = {**_spec(truth, "newtonian")}
    off["bodies"] = [{**off["bodies"][0], "velocity": [0.5 + VELOCITY_POLISH[1] * unit, -2.0]}]
    start = load_scene(off)
    real_solve, calls = fit_module._solve, []

    def stop_at_start_once(method, objective, residuals, y0, c, **kw):
        calls.append(y0)
        if len(calls) == 1:
            return SolverOutcome(y0, [float(jnp.sum(residuals(y0) ** 2))], 0, False, "stopped (test)")
        return real_solve(method, objective, residuals, y0, c, **kw)

    monkeypatch.setattr(fit_module, "_solve", stop_at_start_once)
    untracked = Observation(times=times, positions=np.asarray(traj.x))
    config = FitConfig(stages=None, uncertainty=False)
    result = fit(start.model, start.params, untracked, ["velocity"], config)
    polish = result.stages[0]["polish"]
    assert list(polish["moved"]) == ["velocity[0]"]
    assert polish["moved"]["velocity[0]"] == pytest.approx(-VELOCITY_POLISH[1] * unit, rel=1e-6)
    assert polish["points"] == 1 + 2 * len(VELOCITY_POLISH) * 2 and polish["best_loss"] < 1e-3 * polish["start_loss"]
    assert len(calls) == 2 and any("solved again from there" in n for n in result.notes)
    np.testing.assert_allclose(np.asarray(result.values["velocity"]), [0.5, -2.0], atol=1e-4)
    assert result.converged and result.timing["polish_s"] > 0

    for obs, kw in ((Observation(times=times, positions=np.asarray(traj.x), point_ids="particles"), {}),
                    (untracked, {"polish": ()})):
        calls.clear()
        result = fit(start.model, start.params, obs, ["velocity"], FitConfig(stages=None, uncertainty=False, **kw))
        assert "polish" not in result.stages[0] and len(calls) == 1 and not result.converged
    # a polish that finds no lower loss says so and leaves the stage as it stopped
    calls.clear()
    result = fit(true_scene.model, true_scene.params, untracked, ["velocity"], config)
    assert result.stages[0]["polish"]["moved"] == {} and len(calls) == 1 and not result.converged
    assert any("no velocity move of" in n for n in result.notes)
    with pytest.raises(JaxmpmError, match="polish must be"):
        fit(start.model, start.params, untracked, ["velocity"], FitConfig(polish=(0.0,)))


def test_fit_with_a_scan_starts_from_the_scanned_point_and_records_it():
    """From a guess 2 decades off on a plateau-free track loss the scan must move mu toward the
    truth before LM starts, and fit.json's stage record says so."""
    truth, guess = MATERIAL_CASES["newtonian"]
    true_scene = load_scene(_spec(truth, "newtonian"))
    traj = simulate(true_scene.model, true_scene.params)
    obs = Observation(times=np.asarray(traj.times), positions=np.asarray(traj.x), point_ids="particles")
    start = load_scene(_spec({"model": "newtonian", **truth, "mu": truth["mu"] / 100.0}, "newtonian"))
    result = fit(start.model, start.params, obs, ["mu"], FitConfig(max_steps=1, stages=None, scan=(1.0, 2.0)))
    scan = result.stages[0]["scan"]
    assert scan["moved"] == {"mu": 2.0} and scan["best_loss"] < 1e-6 * scan["start_loss"]
    assert abs(np.log10(float(result.values["mu"]) / truth["mu"])) < 0.01
    with pytest.raises(JaxmpmError, match="scan must be"):
        fit(start.model, start.params, obs, ["mu"], FitConfig(scan=("a",)))


def test_the_default_scans_only_fits_without_per_particle_tracks():
    """FitConfig.scan=None scans SCAN_DECADES when the data do not track every particle (here the
    same points, untracked) and not from tracks of every particle; () never scans."""
    truth, _ = MATERIAL_CASES["newtonian"]
    true_scene = load_scene(_spec(truth, "newtonian"))
    traj = simulate(true_scene.model, true_scene.params)
    start = load_scene(_spec({"model": "newtonian", **truth, "mu": truth["mu"] / 100.0}, "newtonian"))
    tracked = Observation(times=np.asarray(traj.times), positions=np.asarray(traj.x), point_ids="particles")
    untracked = Observation(times=np.asarray(traj.times), positions=np.asarray(traj.x))

    def scan_of(obs, **kw):
        result = fit(start.model, start.params, obs, ["mu"], FitConfig(max_steps=1, stages=None, uncertainty=False, **kw))
        return result.stages[0].get("scan")

    assert scan_of(tracked) is None
    scanned = scan_of(untracked)
    assert scanned["points"] == 1 + len(SCAN_DECADES) and scanned["moved"] == {"mu": 2.0}
    assert scan_of(untracked, scan=()) is None


def test_a_scanned_fit_that_does_not_converge_is_also_run_from_the_guess(monkeypatch):
    """A scan looks at one parameter at a time and can start a stage in another basin: a fit
    whose scan moved its start and that did not converge is run again from the guess without
    the scan, and the lower loss of the last stage decides. Here the scan moves μ from 2.5
    decades below the truth to 0.5 and one LM step cannot converge: the scanned start is
    kept, the guess's run is reported beside it; then, with the other run's loss made the
    lower, it is kept."""
    import importlib
    from dataclasses import replace

    fit_module = importlib.import_module("jaxmpm.fit")
    truth, _ = MATERIAL_CASES["newtonian"]
    true_scene = load_scene(_spec(truth, "newtonian"))
    traj = simulate(true_scene.model, true_scene.params)
    start = load_scene(_spec({"model": "newtonian", **truth, "mu": truth["mu"] * 10**-2.5}, "newtonian"))
    untracked = Observation(times=np.asarray(traj.times), positions=np.asarray(traj.x))
    config = FitConfig(max_steps=1, stages=None, uncertainty=False)
    logs = []
    result = fit(start.model, start.params, untracked, ["mu"], config, log=logs.append)
    with monkeypatch.context() as patched:  # each start alone
        patched.setattr(fit_module, "_also_from_the_guess", lambda scanned, *args, **kwargs: scanned)
        scanned = fit(start.model, start.params, untracked, ["mu"], config)
    guess = fit(start.model, start.params, untracked, ["mu"], replace(config, scan=()))
    moved = scanned.stages[0]["scan"]["moved"]
    assert not scanned.converged and list(moved) == ["mu"]
    assert result.stages[0]["scan"]["moved"] == moved  # the scanned start kept: its loss is lower
    np.testing.assert_array_equal(result.values["mu"], scanned.values["mu"])
    other = result.timing["other_start"]
    assert other["start"] == "guess" and other["loss"] == guess.stages[-1]["loss"]
    np.testing.assert_array_equal(other["values"]["mu"], guess.values["mu"])
    assert result.iterations == scanned.iterations + guess.iterations
    assert any("fitting again from the guess" in line for line in logs)
    assert "kept the scanned start" in result.notes[-1]

    # the choice itself: the guess's run kept where its last stage's loss is lower, and not
    # compared where the two ended on different dt
    def fake_fit(*args, **kwargs):
        return replace(guess, stages=[{**guess.stages[-1], "loss": [1.0, 0.1 * scanned.stages[-1]["loss"][1]]}])

    monkeypatch.setattr(fit_module, "fit", fake_fit)
    chosen = fit_module._also_from_the_guess(scanned, start.model, start.params, untracked, ["mu"], config,
                                             progress=None, log=None)
    assert chosen.values is guess.values and chosen.timing["other_start"]["start"] == "scan"
    assert "kept the guess without the scan" in chosen.notes[-1]
    finer = replace(guess, stages=[{**guess.stages[-1], "substeps": 2 * guess.stages[-1]["substeps"], "loss": [1.0, 0.0]}])
    monkeypatch.setattr(fit_module, "fit", lambda *a, **k: finer)
    chosen = fit_module._also_from_the_guess(scanned, start.model, start.params, untracked, ["mu"], config,
                                             progress=None, log=None)
    assert chosen.values is scanned.values and "differ in frames or dt" in chosen.notes[-1]

    def failing_fit(*args, **kwargs):
        raise fit_module.FitError("unhealthy at the starting point")

    monkeypatch.setattr(fit_module, "fit", failing_fit)
    chosen = fit_module._also_from_the_guess(scanned, start.model, start.params, untracked, ["mu"], config,
                                             progress=None, log=None)
    assert chosen.values is scanned.values and "failed (unhealthy at the starting point)" in chosen.notes[-1]

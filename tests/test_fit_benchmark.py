"""The system-identification benchmark harness (``jaxmpm bench sysid``): its tables, and the
CI-sized preset run end to end (one coarse 3D identification, ~70 s)."""

import importlib
import json

import jax.numpy as jnp
import pytest

from jaxmpm.bench_sysid import (Case, errors, find_case, preset_cases, run_case, run_sysid_bench, scene_spec,
                                sigma_check, summarise, targets, truth_values)
from jaxmpm.scene import load_scene


def test_presets_cover_the_protocol():
    preset, cases = preset_cases("reduced")
    keys = {c.key for c in cases}
    assert len(keys) == len(cases)
    assert {c.material for c in cases} == {"newtonian", "viscoplastic", "sand", "elastic", "plasticine"}
    assert {c.collider for c in cases} >= {"box", "bunny", "armadillo", "side", "small", "large", "bowl", "three"}
    assert {c.mode for c in cases} == {"cpic", "grid", "particles"}
    assert {c.supervision for c in cases} == {"tracks", "silhouettes"}
    assert preset.frames == 16 and preset.views == 11
    _, full = preset_cases("full")
    assert len(full) > len(cases)


@pytest.mark.parametrize("collider", ["box", "bunny", "armadillo", "side", "small", "large", "bowl", "three"])
def test_case_scenes_load_with_the_body_above_the_colliders(collider):
    preset, _ = preset_cases("ci")
    case = Case("newtonian", collider, 0, "tracks", "cpic")
    scene = load_scene(scene_spec(case, preset, truth_values("newtonian", 0)))
    assert scene.model.collision == "cpic"
    assert len(scene.model.colliders) == {"three": 4}.get(collider, 2)
    # every particle starts on the outer side of every collider, clear of its surface
    x0 = jnp.concatenate([b.x0 for b in scene.model.bodies])
    for c in scene.model.colliders:
        sd, _ = c.signed_distance(x0, jnp.zeros((), x0.dtype))
        assert float(jnp.min(sd)) > 0.5 * scene.model.grid.dx, (c.name, float(jnp.min(sd)))


def test_truth_sets_are_deterministic_and_in_range():
    a, b = truth_values("viscoplastic", 3), truth_values("viscoplastic", 3)
    assert a == b and 1e3 <= a["mu"] <= 5e3
    assert truth_values("sand", 0) != truth_values("sand", 1)
    e = errors(["mu", "friction_angle"], {"mu": 110.0, "friction_angle": 30.5}, {"mu": 100.0, "friction_angle": 30.0})
    assert e["mu"] == pytest.approx(0.0414, abs=1e-4) and e["friction_angle"] == pytest.approx(0.5)


def test_summary_table_and_targets():
    row = {"case": {"material": "sand", "collider": "box", "index": 0, "supervision": "tracks", "mode": "cpic"},
           "key": "k", "errors": {"friction_angle": 0.2}, "velocity_error": 0.001, "converged": True,
           "seconds": 100.0, "cpu_seconds": 180.0, "peak_rss_mb": 900.0}
    table = summarise([row, dict(row, errors={"friction_angle": 0.4}, converged=False),
                       {"case": row["case"], "key": "bad", "error": "boom"}])
    assert "| tracks | cpic | sand | box | 2 | 1/2 |" in table and "0.30 ± 0.10" in table and "boom" in table
    assert "1/2 cases within 0.3" in targets([row, dict(row, errors={"friction_angle": 0.4})])


def test_sigma_check_counts_the_truth_within_three_sigma():
    case = {"material": "newtonian", "collider": "box", "index": 0, "supervision": "tracks", "mode": "cpic"}
    row = {"case": case, "key": "k", "converged": True, "errors": {"mu": 0.01, "kappa": 0.1},
           "truth": {"mu": 100.0, "kappa": 1e4}, "estimate": {"mu": 102.0, "kappa": 1.5e4},
           "std": {"mu": 1.0, "kappa": 1e3, "velocity": [0.1, 0.1, 0.1]}}
    text = sigma_check([row, {"case": case, "key": "bad", "error": "boom"}])
    # mu: 2 sigma away, kappa: 5 sigma away; the velocity (no truth) is not counted
    assert text == "* tracks, cpic, converged: 2 parameter estimates, truth at a median of 3.5 σ (max 5); 1 within 3σ"
    resolved = dict(row, key="r", resolution=True, std={"mu": 4.0, "kappa": 1e4})
    assert sigma_check([row, resolved]).splitlines()[1] == (
        "* tracks, cpic, converged, resolved σ: 2 parameter estimates, truth at a median of 0.5 σ (max 0.5); 2 within 3σ")


@pytest.mark.slow  # the harness end to end (90 s here); its parts are tested above
def test_ci_preset_runs_end_to_end(tmp_path):
    code = run_sysid_bench(["--preset", "ci", "--out", str(tmp_path)])
    assert code == 0
    rows = [json.loads(line) for line in (tmp_path / "results.jsonl").read_text().splitlines()]
    assert len(rows) == 1 and "error" not in rows[0], rows
    assert rows[0]["errors"]["mu"] < 0.02 and rows[0]["converged"]
    assert (tmp_path / "table.md").read_text().count("| tracks | cpic | newtonian | box |") == 1


def test_an_output_folder_holds_rows_of_one_dtype(tmp_path, capsys):
    row = {"case": {"material": "newtonian", "collider": "box", "index": 0, "supervision": "tracks", "mode": "cpic"},
           "key": "newtonian-box-0-tracks-cpic", "errors": {"mu": 0.0}, "dtype": "float32"}
    (tmp_path / "results.jsonl").write_text(json.dumps(row) + "\n")
    # refused before any case runs (the ci preset's case is not done in float64)
    assert run_sysid_bench(["--preset", "ci", "--float64", "--out", str(tmp_path)]) == 2
    assert "holds float32 rows; run float64 into another --out" in capsys.readouterr().err
    assert len((tmp_path / "results.jsonl").read_text().splitlines()) == 1


def test_an_output_folder_holds_rows_of_one_velocity_choice(tmp_path, capsys):
    row = {"case": {"material": "newtonian", "collider": "box", "index": 0, "supervision": "tracks", "mode": "cpic"},
           "key": "newtonian-box-0-tracks-cpic", "errors": {"mu": 0.0}, "dtype": "float32", "refine_velocity": False}
    (tmp_path / "results.jsonl").write_text(json.dumps(row) + "\n")
    # refused before any case runs (the ci preset's case is not done with the default, auto)
    assert run_sysid_bench(["--preset", "ci", "--out", str(tmp_path)]) == 2
    assert "holds rows of --refine-velocity no; run --refine-velocity auto into another" in capsys.readouterr().err
    assert len((tmp_path / "results.jsonl").read_text().splitlines()) == 1


def test_an_output_folder_holds_rows_of_one_scan_choice(tmp_path, capsys):
    row = {"case": {"material": "newtonian", "collider": "box", "index": 0, "supervision": "tracks", "mode": "cpic"},
           "key": "newtonian-box-0-tracks-cpic", "errors": {"mu": 0.0}, "dtype": "float32", "refine_velocity": None}
    (tmp_path / "results.jsonl").write_text(json.dumps(row) + "\n")
    # a row from before the option scanned nothing: refused before any case runs
    assert run_sysid_bench(["--preset", "ci", "--scan=-1,1,2,3", "--out", str(tmp_path)]) == 2
    assert "holds rows of --scan none; run --scan -1,1,2,3 into another" in capsys.readouterr().err
    assert len((tmp_path / "results.jsonl").read_text().splitlines()) == 1
    with pytest.raises(SystemExit):  # a malformed --scan is the parser's error, before any work
        run_sysid_bench(["--preset", "ci", "--scan", "1,x", "--out", str(tmp_path / "other")])
    assert "--scan must be auto, none or comma-separated decade offsets" in capsys.readouterr().err
    assert not (tmp_path / "other").exists()


def test_run_case_hands_its_choices_to_the_fit(monkeypatch):
    fit_module = importlib.import_module("jaxmpm.fit")  # the package's ``jaxmpm.fit`` is the function
    seen = {}

    def capture(model, params, observation, names, config, **kwargs):
        seen["config"] = config
        raise RuntimeError("captured")

    monkeypatch.setattr(fit_module, "fit", capture)
    preset, cases = preset_cases("ci")
    with pytest.raises(RuntimeError, match="captured"):
        run_case(cases[0], preset, scan=[-1, 2], refine_velocity=True, resolution=True)
    config = seen["config"]
    assert config.scan == (-1.0, 2.0) and config.refine_velocity is True and config.resolution is True


def test_a_row_records_the_start_not_kept(monkeypatch):
    """Where the fit ran from two starts (a scanned fit that did not converge), the row keeps
    the other run's figures (``FitResult.timing["other_start"]``); None otherwise."""
    from jaxmpm.bench_sysid import FIT_NAMES
    from jaxmpm.fit import FitResult

    fit_module = importlib.import_module("jaxmpm.fit")
    preset, cases = preset_cases("ci")
    values = {n: 1.0 for n in FIT_NAMES[cases[0].material]} | {"velocity": [0.0, -1.0, 0.0]}
    other = {"start": "guess", "total_s": 2.0, "iterations": 4, "loss": [0.5, 0.25], "values": values,
             "converged": False}
    for timing in ({"total_s": 3.0, "other_start": other}, {"total_s": 1.0}):
        def fake(*args, timing=timing, **kwargs):
            return FitResult(params=None, values=values, std={}, loss=[1.0], iterations=3, seconds=1.0,
                             converged=False, message="m", substeps=20, timing=timing)

        monkeypatch.setattr(fit_module, "fit", fake)
        row = run_case(cases[0], preset)
        assert row["other_start"] == timing.get("other_start")
        json.dumps(row)


def test_find_case_by_key():
    preset, case = find_case("newtonian-small-0-tracks-cpic")
    assert case == Case("newtonian", "small", 0, "tracks", "cpic") and preset == preset_cases("reduced")[0]
    with pytest.raises(ValueError, match="jaxmpm bench sysid --preset ci --list"):
        find_case("newtonian-small-0-tracks-cpic", "ci")


def test_a_float64_case_needs_x64_from_its_caller():
    """run_case does not switch JAX's precision itself (the harness's subprocess does): without
    x64 a float64 request is refused before any simulation."""
    preset, case = find_case("newtonian-small-0-tracks-cpic")
    with pytest.raises(ValueError, match="jax_enable_x64"):
        run_case(case, preset, "float64")
    with pytest.raises(ValueError, match="'float32' or 'float64'"):
        run_case(case, preset, "float16")


@pytest.mark.slow  # a diagnostic script of the benchmarks, not the package
def test_the_loss_at_script_evaluates_the_fits_loss_at_chosen_points(tmp_path, capsys):
    """``benchmarks/sysid_loss_at.py``: from tracks of every particle the loss is 0 at the truth
    (to round-off) and grows with a parameter's or the velocity's offset; a line's ends are its two points."""
    import importlib.util
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "benchmarks" / "sysid_loss_at.py"
    spec = importlib.util.spec_from_file_location("sysid_loss_at", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    out = tmp_path / "loss.jsonl"
    assert module.main(["--preset", "ci", "--case", "newtonian-box-0-tracks-cpic", "--offset", "mu=0.05,0.5",
                        "--offset", "velocity.y=0.05", "--at", 'slow={"velocity": [0, -0.9, 0]}',
                        "--line", "truth,slow,3", "--out", str(out)]) == 0
    rows = {r["label"]: r for r in map(json.loads, out.read_text().splitlines())}
    assert rows["truth"]["loss"] < 1e-12  # round-off of the values' log10 round trip
    assert 0.0 < rows["mu +0.05"]["loss"] < rows["mu +0.5"]["loss"]
    assert rows["velocity.y +0.05"]["loss"] > 0.0
    assert rows["truth -> slow 0"]["loss"] == rows["truth"]["loss"] and rows["truth -> slow 1"]["loss"] == rows["slow"]["loss"]
    assert 0.0 < rows["truth -> slow 0.5"]["loss"] < rows["slow"]["loss"]
    with pytest.raises(SystemExit):  # a malformed point is the parser's error, before any simulation
        module.main(["--preset", "ci", "--case", "newtonian-box-0-tracks-cpic", "--offset", "mu"])
    assert "expected NAME=d1,d2" in capsys.readouterr().err

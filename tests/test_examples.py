"""Smoke tests of every file in examples/: each scene loads and runs its first substeps without
NaN, and each case-study script builds its sequences (data, scenes, observations) and runs
its first frames at a coarse resolution."""

from __future__ import annotations

import dataclasses
import importlib.util
import sys
from pathlib import Path

import equinox as eqx
import numpy as np
import pytest

from jaxmpm.scene import load_scene
from jaxmpm.step import simulate

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


@eqx.filter_jit
def _rollout(model, params, frames: int):
    """One compiled rollout per model structure (scenes that differ only in parameters share it)."""
    return simulate(model, params, checkpoint=None, frames=frames)


def _first_steps(model, params, steps: int = 4, frames: int = 3):
    """Positions over the first ``(frames - 1) * steps`` substeps at the scene's own dt,
    ``(frames, N, D)``; fails on NaN or particles leaving the domain."""
    model = dataclasses.replace(model, frame_dt=model.dt * steps, substeps=steps)
    traj = _rollout(model, params, frames)
    assert not np.asarray(traj.nan).any()
    assert int(np.asarray(traj.left).max()) == 0
    return np.asarray(traj.x)


def _script(name: str):
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_every_example_is_covered():
    files = {p.name for p in EXAMPLES.iterdir() if p.is_file()}
    assert files == {f"{n}.toml" for n in TOMLS} | {"dam_break_2d.py", "dam_break_3d_obstacle.py"}


TOMLS = ("bowl", "bunny", "droplet", "droplet_guess")


@pytest.mark.parametrize("name", TOMLS)
def test_example_scene_runs(name):
    scene = load_scene(EXAMPLES / f"{name}.toml")
    x = _first_steps(scene.model, scene.params)
    assert np.all(np.isfinite(x)) and x.shape[1] == scene.model.num_particles
    assert np.abs(x[1] - x[0]).max() > 0  # something moved


def test_dam_break_2d_builds_its_three_columns_and_they_collapse():
    module = _script("dam_break_2d")
    sequences = module.sequences(cells=3)
    assert [s.name for s in sequences] == ["mm_large", "ko", "mm_small"]
    for s in sequences:
        assert s.observation.probe_names == ("front_x",) and len(s.observation.times) > 5
    model, params = sequences[0].model, sequences[0].params
    x = _first_steps(model, params, steps=model.substeps, frames=4)
    assert x[-1, :, 0].max() > x[0, :, 0].max()  # the front has started to run out


def test_dam_break_3d_obstacle_builds_its_sequence_and_runs():
    module = _script("dam_break_3d_obstacle")
    seq = module.sequence(dx=0.2, t_end=0.1)
    assert len(seq.observation.probe_names) == 4 and set(seq.probes) == set(seq.observation.probe_names)
    x = _first_steps(seq.model, seq.params, steps=seq.model.substeps, frames=3)
    assert x[-1, :, 0].min() < x[0, :, 0].min()  # the water moves towards the obstacle (−x)

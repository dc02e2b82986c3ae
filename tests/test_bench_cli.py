"""``jaxmpm bench`` from an installed package: the jaxmpm rows are measured, the Taichi/Warp
peers (``benchmarks/peers/``, only in a source checkout) are reported unavailable in one line."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import jaxmpm


def test_bench_step_runs_from_an_installed_package(tmp_path):
    # What a wheel installs: the jaxmpm package alone, no benchmarks/ folder beside it.
    site = tmp_path / "site"
    shutil.copytree(Path(jaxmpm.__file__).parent, site / "jaxmpm", ignore=shutil.ignore_patterns("__pycache__"))
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site), "JAX_PLATFORMS": "cpu"}
    cmd = [sys.executable, "-m", "jaxmpm.cli", "bench", "step", "--particles", "64", "--grid", "16", "--steps", "1",
           "--materials", "elastic", "--modes", "forward"]
    proc = subprocess.run(cmd, cwd=work, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = proc.stdout
    assert "Traceback" not in proc.stderr
    assert out.count("Taichi/Warp: not available") == 1, out
    row = [line for line in out.splitlines() if line.startswith("jaxmpm elastic forward")]
    assert len(row) == 1, out
    ms_per_step = float(row[0].split()[3])
    assert ms_per_step > 0


def test_bench_grad_runs_from_an_installed_package(tmp_path):
    # `jaxmpm bench grad` without the Taichi peer beside it: the Taichi row says why, the jaxmpm
    # rows (reverse mode against its own forward, forward-mode Jacobians) are measured.
    site = tmp_path / "site"
    shutil.copytree(Path(jaxmpm.__file__).parent, site / "jaxmpm", ignore=shutil.ignore_patterns("__pycache__"))
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site), "JAX_PLATFORMS": "cpu"}
    cmd = [sys.executable, "-m", "jaxmpm.cli", "bench", "grad", "--particles", "64", "--grid", "16", "--steps", "2",
           "--ks", "2", "--repeats", "1"]
    proc = subprocess.run(cmd, cwd=work, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = proc.stdout
    assert "Traceback" not in proc.stderr
    taichi = [line for line in out.splitlines() if line.startswith("Taichi ti.ad.Tape forward+backward")]
    assert len(taichi) == 1 and "skipped" in taichi[0], out
    assert len([line for line in out.splitlines() if line.startswith("jaxmpm reverse (x own forward)")]) == 1, out
    for k in (2,):  # two tangents, vmapped
        row = [line for line in out.splitlines() if line.startswith(f"jaxmpm jvp Jacobian, k = {k}")]
        assert len(row) == 1, out
        assert float(row[0].split()[-4]) > 0  # the ratio to the forward rollout

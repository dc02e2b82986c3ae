"""``jaxmpm bench`` from an installed package: the jaxmpm rows are measured, the Taichi/Warp
peers (``benchmarks/peers/``, only in a source checkout) are reported unavailable in one line."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import jaxmpm


def _bench_installed(tmp_path, *args: str) -> str:
    """``jaxmpm bench ARGS`` run as a wheel installs it (the jaxmpm package alone, no
    benchmarks/ folder beside it, from another directory); returns its stdout."""
    site = tmp_path / "site"
    shutil.copytree(Path(jaxmpm.__file__).parent, site / "jaxmpm", ignore=shutil.ignore_patterns("__pycache__"))
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site), "JAX_PLATFORMS": "cpu"}
    proc = subprocess.run([sys.executable, "-m", "jaxmpm.cli", "bench", *args], cwd=work, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    return proc.stdout


def test_bench_step_runs_from_an_installed_package(tmp_path):
    out = _bench_installed(tmp_path, "step", "--particles", "64", "--grid", "16", "--steps", "1",
                           "--materials", "elastic", "--modes", "forward")
    assert out.count("Taichi/Warp: not available") == 1, out
    row = [line for line in out.splitlines() if line.startswith("jaxmpm elastic forward")]
    assert len(row) == 1, out
    ms_per_step = float(row[0].split()[3])
    assert ms_per_step > 0


@pytest.mark.slow  # 60 s here; the installed-package path is the step benchmark's above
def test_bench_grad_runs_from_an_installed_package(tmp_path):
    # `jaxmpm bench grad` without the Taichi peer beside it: the Taichi row says why, the jaxmpm
    # rows (reverse mode against its own forward, forward-mode Jacobians) are measured.
    out = _bench_installed(tmp_path, "grad", "--particles", "64", "--grid", "16", "--steps", "2", "--ks", "2",
                           "--repeats", "1")
    taichi = [line for line in out.splitlines() if line.startswith("Taichi ti.ad.Tape forward+backward")]
    assert len(taichi) == 1 and "skipped" in taichi[0], out
    assert len([line for line in out.splitlines() if line.startswith("jaxmpm reverse (x own forward)")]) == 1, out
    for k in (2,):  # two tangents, vmapped
        row = [line for line in out.splitlines() if line.startswith(f"jaxmpm jvp Jacobian, k = {k}")]
        assert len(row) == 1, out
        assert float(row[0].split()[-4]) > 0  # the ratio to the forward rollout

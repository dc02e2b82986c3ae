"""The persistent compilation cache: where it lives, how it is turned off, and that the
command line writes its compiled programs there and a second run loads them."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from test_cli import TINY_SCENE

from jaxmpm.cache import CACHE_ENV, default_cache_dir


def test_the_cache_folder_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "here"))
    assert default_cache_dir() == tmp_path / "here"
    for off in ("", "off", " OFF "):
        monkeypatch.setenv(CACHE_ENV, off)
        assert default_cache_dir() is None
    monkeypatch.delenv(CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_dir() == tmp_path / "xdg" / "jaxmpm" / "xla"


def _simulate(tmp_path: Path, cache: str) -> tuple[set[str], str]:
    scene = tmp_path / "scene.toml"
    scene.write_text(TINY_SCENE.format(mu=1.0))
    env = {**os.environ, CACHE_ENV: cache, "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
           "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": "0", "JAX_LOG_COMPILES": "1"}
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    run = subprocess.run([sys.executable, "-m", "jaxmpm.cli", "simulate", str(scene), "--out", str(tmp_path / "o.npz")],
                         env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    return (set(os.listdir(cache)) if os.path.isdir(cache) else set()), run.stderr


def test_the_command_line_writes_its_programs_to_the_cache_and_reads_them_back(tmp_path):
    cache, hit = str(tmp_path / "cache"), "Persistent compilation cache hit"
    written, log = _simulate(tmp_path, cache)
    first_hits = log.count(hit)  # a run may load what it wrote itself (a program compiled twice)
    assert written
    again, log = _simulate(tmp_path, cache)
    assert again == written and log.count(hit) >= len(written) > first_hits  # loaded every program, wrote none
    nothing, log = _simulate(tmp_path, "off")  # turned off: no folder named "off", nothing read
    assert nothing == set() and hit not in log and not Path("off").exists()

"""The persistent compilation cache: compiled programs are written to disk and later runs of
the same programs (the same scene layout, the same stage of a fit) load them instead of
compiling again.

Compilation dominates small runs on a CPU: for ``jaxmpm demo --video --quick`` (281
particles) XLA spent ~30 s on the fit's residual-and-Jacobian program and ~15 s on a forward
rollout, which then ran in 0.1–0.5 s (docs/benchmarks.md; about half that since the step's
size was halved). JAX's own cache (``jax_compilation_cache_dir``) keeps
programs that took more than a second to compile. The command line turns it on
(:func:`enable_compilation_cache`); a library user calls that function once, before any
compilation.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["CACHE_ENV", "default_cache_dir", "enable_compilation_cache"]

#: Environment variable naming the cache folder; empty or ``off`` turns the cache off.
CACHE_ENV = "JAXMPM_CACHE_DIR"


def default_cache_dir() -> Path | None:
    """``$JAXMPM_CACHE_DIR``, else ``$XDG_CACHE_HOME/jaxmpm/xla`` (``~/.cache/jaxmpm/xla``);
    None when ``JAXMPM_CACHE_DIR`` is empty or ``off``."""
    value = os.environ.get(CACHE_ENV)
    if value is not None:
        return None if value.strip().lower() in ("", "off") else Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "jaxmpm" / "xla"


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path | None:
    """Turn on JAX's persistent compilation cache in ``path`` (default
    :func:`default_cache_dir`) and return the folder used.

    A cache folder the user already gave JAX (``JAX_COMPILATION_CACHE_DIR`` or
    ``jax.config``) is left as it is and returned. Returns None, changing nothing, when the
    cache is turned off (``JAXMPM_CACHE_DIR=off``) or the folder cannot be created. Call it
    before the first compilation: programs compiled earlier are not written.

    The cache is trusted code: do not point it at a folder others can write to.
    """
    import jax

    current = jax.config.jax_compilation_cache_dir
    if current:
        return Path(current)
    folder = Path(path).expanduser() if path is not None else default_cache_dir()
    if folder is None:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    return folder

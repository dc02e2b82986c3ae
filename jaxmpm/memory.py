"""How much memory a run will need, estimated before it starts, and the limit it must fit in.

The estimate is a floor of what one forward run holds at once (a fit or a discovery needs
more): the per-frame outputs, the particles' working set in a step, the grid and the
collision fields. It exists so that a scene that cannot run (``frames = 1e9``, a grid of a
billion nodes, eighty million particles) is refused in one line with the number, instead of
growing until the operating system kills it.
"""

from __future__ import annotations

import os

from .errors import SceneError

#: Used as the limit when the machine's available memory cannot be read.
FALLBACK_LIMIT_BYTES = 16 * 2**30

#: Environment variable that overrides the limit (in GB, 1e9 bytes), e.g. to allow a run
#: on a machine with swap, or to test the check.
LIMIT_ENV = "JAXMPM_MEMORY_LIMIT_GB"


def particle_floats(dim: int) -> int:
    """Floats one particle holds during a step: the state (x, v, C, F, mass, volume, material
    state) and the step's temporaries (trial F, its SVD, the stress, stencil weights), about
    ``12 D^2 + 12 D + 12`` (84 in 2D). Measured: a 2D float32 run of 3 frames peaks at 408
    bytes per particle more RSS (750k -> 3M particles), this estimate gives 336 + 96 (frames)."""
    return 12 * dim * dim + 12 * dim + 12


def node_floats(dim: int) -> int:
    """Floats one grid node holds during a step: mass, momentum, velocity and the scatter's
    temporaries, about ``3 D + 3``."""
    return 3 * dim + 3


def estimate(dim: int, particles: int, nodes: int, frames: int, fields: int, itemsize: int) -> dict[str, float]:
    """Bytes a forward run needs, by part.

    Arguments:
        dim: 2 or 3.
        particles: number of particles N.
        nodes: number of grid nodes G.
        frames: number of output frames T (each keeps positions and velocities, ``N x D`` each,
            held twice while they are stacked at the end).
        fields: number of colliders with a precomputed collision field (every non-plane one).
        itemsize: bytes per float (4 for float32, 8 for float64).

    Returns:
        ``{"observation": b, "particles": b, "grid": b, "collision fields": b}`` in bytes.
    """
    return {
        "observation": 4.0 * frames * particles * dim * itemsize,
        "particles": float(particles) * particle_floats(dim) * itemsize,
        "grid": float(nodes) * node_floats(dim) * itemsize,
        "collision fields": float(fields) * nodes * ((dim + 1) * itemsize + 2),
    }


def limit() -> tuple[float, str]:
    """The memory a run may use, in bytes, and where that number comes from.

    ``JAXMPM_MEMORY_LIMIT_GB`` if set; else the machine's available memory (``MemAvailable`` of
    ``/proc/meminfo``, or ``os.sysconf`` free pages); else :data:`FALLBACK_LIMIT_BYTES`.
    """
    text = os.environ.get(LIMIT_ENV)
    if text:
        try:
            value = float(text)
        except ValueError:
            raise SceneError(f"{LIMIT_ENV} must be a number of GB, got {text!r}") from None
        if not value > 0:
            raise SceneError(f"{LIMIT_ENV} must be > 0, got {text!r}")
        return value * 1e9, LIMIT_ENV
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0, "the available memory"
    except OSError:
        pass
    try:
        return float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")), "the free memory"
    except (AttributeError, ValueError, OSError):
        return float(FALLBACK_LIMIT_BYTES), "the assumed memory"


def check(parts: dict[str, float]) -> None:
    """Refuse a run whose estimate exceeds :func:`limit`.

    Arguments:
        parts: bytes by part, from :func:`estimate`.

    Raises:
        SceneError: one line with the total and its parts in GB, the limit, and what to change
            (from the largest part: fewer frames, a larger dx, a lower ppc).
    """
    total = sum(parts.values())
    cap, source = limit()
    if total <= cap:
        return
    shown = ", ".join(f"{name} {b / 1e9:.3g} GB" for name, b in sorted(parts.items(), key=lambda kv: -kv[1]) if b >= 0.01 * total)
    raise SceneError(
        f"scene: this run needs about {total / 1e9:.3g} GB ({shown}), more than {source} "
        f"({cap / 1e9:.3g} GB); {_advice(parts)}"
    )


def _advice(parts: dict[str, float]) -> str:
    """What to change, from the largest part of an estimate."""
    largest = max(parts, key=parts.get)
    return {
        "observation": "use fewer frames",
        "particles": "use a lower ppc or a larger dx",
        "grid": "use a larger dx or a smaller domain",
        "collision fields": "use a larger dx or fewer colliders",
    }[largest]

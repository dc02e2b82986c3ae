"""What is known about one physical parameter, declared once.

A :class:`Parameter` holds a parameter's units, its valid range (checked when a scene is
loaded), the space it is fitted in (a :class:`Transform`: log10, tanh-bounded or linear),
Adam's learning rate in that space and PAC-NeRF's initial guess. Materials declare theirs
next to their constitutive law (:attr:`jaxmpm.constitutive.Material.parameters`); the
parameters every body, collider and scene has are declared here. Scene validation, the fit's
transforms, the CLI's ``--params``, sweeps, discovery and reports read these declarations.
"""

from __future__ import annotations

import abc
import math
from dataclasses import dataclass

import equinox as eqx
import jax.numpy as jnp

__all__ = [
    "Range",
    "POSITIVE",
    "NON_NEGATIVE",
    "POISSON",
    "ANGLE",
    "UNIT_INTERVAL",
    "ANY",
    "Transform",
    "Log10",
    "TanhBounded",
    "Linear",
    "Parameter",
    "DENSITY",
    "VELOCITY",
    "OFFSET",
    "GRAVITY",
    "FRICTION",
    "RESTITUTION",
    "BODY_PARAMETERS",
    "COLLIDER_PARAMETERS",
]


class Range:
    """An allowed open/closed interval of a parameter's physical value, for validation."""

    def __init__(self, lo=-math.inf, hi=math.inf, lo_open=True, hi_open=True, text=""):
        self.lo, self.hi, self.lo_open, self.hi_open, self.text = lo, hi, lo_open, hi_open, text

    def __contains__(self, value: float) -> bool:
        above = value > self.lo if self.lo_open else value >= self.lo
        below = value < self.hi if self.hi_open else value <= self.hi
        return bool(above and below and math.isfinite(value))


POSITIVE = Range(0.0, text="> 0")
NON_NEGATIVE = Range(0.0, lo_open=False, text=">= 0")
POISSON = Range(-1.0, 0.5, text="in (-1, 0.5)")
ANGLE = Range(0.0, 90.0, text="in (0, 90) degrees")
UNIT_INTERVAL = Range(0.0, 1.0, lo_open=False, hi_open=False, text="in [0, 1]")
ANY = Range(text="finite")


# --------------------------------------------------------------------------- fitting spaces


class Transform(eqx.Module):
    """The map between a parameter's physical value and the variable an optimiser moves."""

    @abc.abstractmethod
    def to_unconstrained(self, value):
        """Physical value -> optimisation variable (elementwise, traceable)."""

    @abc.abstractmethod
    def from_unconstrained(self, y):
        """Optimisation variable -> physical value (elementwise, traceable)."""

    def bounds(self) -> tuple[float, float]:
        """Bounds of the optimisation variable for bounded solvers (default: none)."""
        return -math.inf, math.inf

    def needs_positive(self) -> bool:
        """Whether the physical value must be > 0 to be mapped (log spaces)."""
        return False


class Log10(Transform):
    """``y = log10(value)``: moduli, viscosities, densities (PAC-NeRF's space)."""

    def to_unconstrained(self, value):
        return jnp.log10(value)

    def from_unconstrained(self, y):
        return 10.0**y

    def needs_positive(self) -> bool:
        return True


class TanhBounded(Transform):
    """``value = mid + half tanh((y - mid) / half)`` on ``(lo, hi)`` (PAC-NeRF's Poisson ratio).

    Bounded solvers keep ``y`` within ``mid ± 2.5 half``, out of the tanh's saturation where
    its slope vanishes.
    """

    lo: float
    hi: float

    def _mid_half(self):
        return (self.lo + self.hi) / 2, (self.hi - self.lo) / 2

    def to_unconstrained(self, value):
        mid, half = self._mid_half()
        return mid + half * jnp.arctanh((value - mid) / half)

    def from_unconstrained(self, y):
        mid, half = self._mid_half()
        return mid + half * jnp.tanh((y - mid) / half)

    def bounds(self) -> tuple[float, float]:
        mid, half = self._mid_half()
        return mid - 2.5 * half, mid + 2.5 * half


class Linear(Transform):
    """``y = value``: angles in degrees, velocities, gravity, friction coefficients."""

    def to_unconstrained(self, value):
        return value

    def from_unconstrained(self, y):
        return y


@dataclass(frozen=True)
class Parameter:
    """One physical parameter, declared once.

    Attributes:
        name: the key in a scene file and in the parameter pytree (``"mu"``, ``"E"``, ...).
        unit: SI units (``"Pa"``, ``"Pa s"``, ``"deg"``, ``"m/s"``, ``""``).
        range: the physically valid values (scene validation).
        transform: the space it is fitted in.
        learning_rate: Adam's step in the optimisation space (PAC-NeRF's
            ``physical_params`` rates where PAC-NeRF fits it, anchors §1.5).
        guess: PAC-NeRF's initial guess for its 45-sequence batch (anchors §1.8), or None.
        description: one line for docs, reports and ``--help``.
    """

    name: str
    unit: str
    range: Range
    transform: Transform
    learning_rate: float
    guess: float | None = None
    description: str = ""

    def check(self, value: float, where: str) -> str | None:
        """A one-line complaint when ``value`` is outside :attr:`range`, else None."""
        if value not in self.range:
            return f"{where}: {self.name} = {value} is out of range (must be {self.range.text})"
        return None


#: Mass density of a body (kg/m^3); fitted in log10 like PAC-NeRF's.
DENSITY = Parameter("density", "kg/m^3", POSITIVE, Log10(), 0.1, None, "mass density")
#: A body's initial velocity (m/s), a vector; GIC's velocity stage uses 1e-2..5e-2 m/s rates.
VELOCITY = Parameter("velocity", "m/s", ANY, Linear(), 0.05, None, "initial velocity of the body")
#: A rigid translation of a body's initial positions (m), a vector, 0 by default: where a body
#: reconstructed from views sits a little off (a visual hull's carving is not symmetric), a
#: velocity fitted to the first frames alone would otherwise absorb the offset (offset / frame
#: interval: 1 mm at 24 fps is 0.024 m/s).
OFFSET = Parameter("offset", "m", ANY, Linear(), 0.002, None, "rigid translation of the body's initial positions")
#: The scene's gravity vector (m/s^2).
GRAVITY = Parameter("gravity", "m/s^2", ANY, Linear(), 0.1, None, "gravitational acceleration")
#: A collider's Coulomb friction coefficient (used with ``contact = "friction"``).
FRICTION = Parameter("friction", "", NON_NEGATIVE, Linear(), 0.02, None, "Coulomb friction coefficient of a collider")
#: A collider's coefficient of restitution of the normal velocity.
RESTITUTION = Parameter("restitution", "", UNIT_INTERVAL, Linear(), 0.02, None, "coefficient of restitution of a collider")

#: Parameters every body has besides its material's.
BODY_PARAMETERS = {p.name: p for p in (DENSITY, VELOCITY, OFFSET)}
#: Parameters every collider has.
COLLIDER_PARAMETERS = {p.name: p for p in (FRICTION, RESTITUTION)}

"""The numerical checks shared by :func:`jaxmpm.fit.fit` and :func:`jaxmpm.discover.discover`:
a fitted model rerun with dt halved or with the other transfer (APIC / the FLIP blend), to
tell the discretisation's error from the data's.

Halving dt measures the time discretisation's error (the dt/2 check); swapping the transfers
measures part of the spatial one, which dt/2 cannot see: at least one of the two transfers is
at least half the change from the converged answer (docs/discover.md, "The transfer check";
docs/fitting.md, "Numerical error of the parameters").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, TypeVar

from .model import Model

__all__ = ["CHECK_FLIP", "Numerics", "other_flip", "transfer_name", "transfer_runs"]

Run = TypeVar("Run")
Same = TypeVar("Same")

#: The FLIP blend the transfer check runs an APIC model with (docs/materials.md, "Transfers").
CHECK_FLIP = 0.99


@dataclass(frozen=True)
class Numerics:
    """How a check changes a model's numerics (the default changes nothing).

    Attributes:
        substeps_factor: substeps per frame multiplied by this (2: the ``dt / 2`` check).
        other_transfer: run the other transfer: an APIC model (``flip = 0``) with the FLIP
            blend :data:`CHECK_FLIP`, a blended one with APIC (the transfer check).
    """

    substeps_factor: int = 1
    other_transfer: bool = False

    def apply(self, model: Model) -> Model:
        if self.substeps_factor != 1:
            model = model.with_substeps(model.substeps * self.substeps_factor)
        if self.other_transfer:
            model = model.with_flip(other_flip(model.flip))
        return model


def other_flip(flip: float) -> float:
    """The blend the transfer check compares a model of blend ``flip`` with."""
    return CHECK_FLIP if flip == 0.0 else 0.0


def transfer_name(flip: float) -> str:
    """``"APIC"`` or ``"the FLIP blend <flip>"``."""
    return "APIC" if flip == 0.0 else f"the FLIP blend {flip:g}"


def transfer_runs(rerun: Callable[["Numerics"], Run], at_dt: Same, at_half: Same,
                  healthy: Callable[[Run], bool]) -> tuple[int, Same, Run]:
    """The transfer check's pair, ``(substeps_factor, same transfer, other transfer)``: the
    other transfer run at dt (``rerun(Numerics(other_transfer=True))``) beside ``at_dt`` (what
    the fitted numerics give); where that run is unhealthy (the FLIP blend may need a
    smaller dt than APIC), at dt/2 beside ``at_half`` (the dt/2 check's). Where both are
    unhealthy, the dt/2 pair."""
    for factor, same in ((1, at_dt), (2, at_half)):
        other = rerun(Numerics(substeps_factor=factor, other_transfer=True))
        if healthy(other):
            break
    return factor, same, other

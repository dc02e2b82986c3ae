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
from typing import Any, Callable, Sequence, TypeVar

import numpy as np

from .model import Model

__all__ = ["CHECK_FLIP", "NUMERICS_BOUND_MOVE", "NUMERICS_NOTE_STDS", "NUMERICS_REFIT_STEPS", "Numerics", "Refit", "format_std", "move_table",
           "numerics_notes", "other_flip", "parameter_moves", "transfer_name", "transfer_runs"]

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

    def describe(self, flip: float) -> str:
        """These numerics for a model of blend ``flip``, in words: e.g. ``"at dt/2"``, ``"with
        APIC at dt/2"`` (empty for the default)."""
        return " ".join(([f"with {transfer_name(other_flip(flip))}"] if self.other_transfer else [])
                        + ([f"at dt/{self.substeps_factor}"] if self.substeps_factor != 1 else []))

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


#: The Levenberg–Marquardt iterations of each of :func:`parameter_moves`' refits, from the
#: fitted point (one Gauss–Newton step underestimated a move 5x where the loss is far from
#: quadratic: a viscosity near 0 with APIC, docs/fitting.md).
NUMERICS_REFIT_STEPS = 4

#: :func:`numerics_notes` names a parameter that a numerics check moves by more than this many
#: of its standard deviations.
NUMERICS_NOTE_STDS = 2.0

#: ... and one held on a bound (a std of 0, in ``discover``) that it moves off the bound by more
#: than this, in optimisation units: Levenberg–Marquardt's step tolerance ``max(rtol, 1e-3) (1 +
#: |y|)`` at ``y = 0``, below which a refit resolves no move.
NUMERICS_BOUND_MOVE = 1e-3


@dataclass(frozen=True)
class Refit:
    """Where a short refit with other numerics ended.

    Attributes:
        y: the fitted variables by name (optimisation space: decades for log10 parameters).
        losses: the loss where it started and the lowest it reached.
        iterations: its Levenberg–Marquardt iterations.
        converged: whether it stopped on its tolerances rather than on its iteration budget.
    """

    y: dict
    losses: tuple[float, float]
    iterations: int
    converged: bool


def _plain(v):
    v = np.asarray(v, float)
    return v.item() if v.ndim == 0 else v.tolist()


def parameter_moves(refit: Callable[[Numerics], "Refit | None"], y: dict, physical: Callable[[str, Any], Any], *,
                    substeps: int, flip: float) -> dict:
    """How the fitted variables ``y`` (optimisation space, by name) depend on the numerics:
    where a short refit from ``y`` ends with dt halved and where one with the other transfer
    ends (:func:`transfer_runs`: at dt, or both transfers at dt/2 where the other one's run is
    unhealthy at dt).

    The dt/2 move estimates the time discretisation's error of the parameters (about the whole
    of it for a first-order scheme); the transfer move, part of the spatial one, which dt/2
    cannot see (at least one transfer is at least half of it from the converged answer).

    Arguments:
        refit: ``refit(numerics)``, the fit's problem with those numerics refitted from ``y``
            by at most :data:`NUMERICS_REFIT_STEPS` iterations; None where its rollout is
            unhealthy at ``y``. (The transfer move at dt/2 is between the two refits' ends.)
        physical: ``physical(name, value)``, an optimisation variable's physical value.
        substeps, flip: the fitted model's substeps per frame and FLIP blend.

    Returns:
        ``{"dt": check, "transfer": check}``, each check ``{"substeps", "loss" ([at its start,
        after the refit]), "iterations", "converged", "shift_y" and "shift" (by name: the move
        in optimisation space, e.g. decades, and in physical units)}``; the transfer check also
        has ``flip`` and ``flip_checked``. Where a refit could not start, its entries are None.
    """
    def record(start: dict | None, run: Refit | None, **which) -> dict:
        if start is None or run is None:
            return {**which, "loss": None, "iterations": None, "converged": None, "shift_y": None, "shift": None}
        return {**which, "loss": [float(run.losses[0]), float(run.losses[1])], "iterations": int(run.iterations),
                "converged": bool(run.converged),
                "shift_y": {n: _plain(np.asarray(run.y[n]) - np.asarray(start[n])) for n in y},
                "shift": {n: _plain(np.asarray(physical(n, run.y[n])) - np.asarray(physical(n, start[n]))) for n in y}}

    half = refit(Numerics(substeps_factor=2))
    factor, start, other = transfer_runs(refit, y, None if half is None else half.y, lambda run: run is not None)
    return {"dt": record(y, half, substeps=2 * substeps),
            "transfer": record(start, other, substeps=factor * substeps, flip=flip, flip_checked=other_flip(flip))}


def move_table(check: dict, names: Sequence[str]) -> dict:
    """The moves of :func:`parameter_moves`' ``check`` by name, physical units: ``{name: {"dt":
    move, "transfer": move}}`` (None where that refit could not start)."""
    return {n: {k: None if check[k]["shift"] is None else check[k]["shift"][n] for k in ("dt", "transfer")}
            for n in names}


def format_std(v) -> str:
    """A std or move for a note: 3 significant digits, arrays as lists."""
    return np.array2string(np.asarray(v, float), precision=3, floatmode="maxprec") if np.ndim(v) else f"{float(v):.3g}"


def numerics_notes(check: dict, names: Sequence[str], std: dict, *, made_by_model: bool, refit: str = "fit") -> list[str]:
    """One note per name of ``names`` that :func:`parameter_moves`' ``check`` moves by more than
    :data:`NUMERICS_NOTE_STDS` of its standard deviation ``std[name]`` (physical units): its
    error is then numerical more than statistical. An entry with a std of 0 (held on a bound)
    is named when a refit moves it off the bound by more than :data:`NUMERICS_BOUND_MOVE`
    (optimisation units). There is no note without a std, and none where the data may have been
    made by this model on its grid (``made_by_model``:
    :meth:`jaxmpm.observe.Observation.made_by`), whose discretisation is then the data's. A
    move from a refit stopped by its iteration budget is a rough one, as the note says: it can
    fall short of the converged refit's, or overshoot it where the loss has a valley
    (docs/discover.md). ``refit`` names the command the note tells the user to rerun
    (``"fit"``, ``"rerun discover"``)."""
    if made_by_model:
        return []
    transfer = check["transfer"]
    what = {"dt": ("at dt/2", f"{refit} with more substeps per frame"),
            "transfer": (f"with {transfer_name(transfer['flip_checked'])} in place of {transfer_name(transfer['flip'])}"
                         + (" (both at dt/2)" if transfer["substeps"] == check["dt"]["substeps"] else ""),
                         f"{refit} with the scene key flip = {CHECK_FLIP:g} or at a finer dx" if transfer["flip"] == 0.0
                         else f"{refit} at a finer dx")}
    rough = "its refit had not converged, so the move is a rough one"
    notes = []
    for n in names:
        if n not in std:
            continue
        sd = np.asarray(std[n], float)
        # a std of 0: held on a bound (discover); a move off it is compared with the solver's resolution
        scaled, pinned = sd > 0, sd == 0
        told, fixes = [], []
        for k in what:
            if check[k]["shift"] is None:
                continue
            move = np.asarray(check[k]["shift"][n], float)
            stds = float(np.max(np.abs(move)[scaled] / sd[scaled])) if np.any(scaled) else 0.0
            off = bool(np.any(np.abs(np.asarray(check[k]["shift_y"][n], float))[pinned] > NUMERICS_BOUND_MOVE))
            if stds > NUMERICS_NOTE_STDS or off:
                why = ([f"{stds:.3g} std"] if stds > NUMERICS_NOTE_STDS else []) + (
                    ["off the bound the fit holds it on"] if off else []) + ([rough] if check[k]["converged"] is False else [])
                told.append(f"{what[k][0]} by {format_std(move)} ({'; '.join(why)})")
                fixes.append(what[k][1])
        if told:
            notes.append(f"{n} would move {'; '.join(told)} (a short refit; its std {format_std(sd)}): its error is "
                         f"numerical more than statistical; to see where it converges, {'; '.join(fixes)} "
                         "(docs/fitting.md, 'Numerical error of the parameters')")
    return notes

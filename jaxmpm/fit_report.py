"""A fit's result as the user sees it: the terminal table and the ``fit.json`` file (DESIGN §5.3).

Used by the ``jaxmpm fit`` command and by ``jaxmpm demo`` (library code never imports the CLI).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def write_json(path: Path, payload: dict) -> None:
    """Write ``payload`` as indented JSON, atomically (a temporary file in the same folder, then a rename)."""
    from .observe import atomic_write

    def write(tmp):
        Path(tmp).write_text(json.dumps(payload, indent=2) + "\n")

    atomic_write(path, write)


def aligned(rows: list[tuple[str, ...]], rule: bool = False) -> list[str]:
    """Rows of strings as lines of left-aligned columns two spaces apart; with ``rule``, a line
    of dashes under the first (the header)."""
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)) for r in rows]
    if rule:
        lines.insert(1, "  ".join("-" * w for w in widths))
    return lines


#: The numerics check's moves as table columns: ``(FitResult.numerics key, header)``.
NUMERICS_COLUMNS = (("dt", "dt/2 move"), ("transfer", "transfer move"))


def numerics_columns(moves: dict) -> tuple[tuple[str, str], ...]:
    """:data:`NUMERICS_COLUMNS` where a numerics check gave ``moves`` (``{name: {"dt": move,
    "transfer": move}}``: ``FitResult.numerics``, ``Discovery.numerics``), else none."""
    return NUMERICS_COLUMNS if moves else ()


def numerics_cells(moves: dict, name: str) -> tuple[str, ...]:
    """Parameter ``name``'s cells of :func:`numerics_columns`."""
    return tuple(format_value(moves.get(name, {}).get(key)) for key, _ in numerics_columns(moves))


def format_table(result, truth: dict | None = None) -> str:
    """The parameters of a :class:`~jaxmpm.fit.FitResult` as an aligned text table.

    Columns: parameter, initial, estimate, std; with the numerics check
    (``result.numerics``) the moves of a refit at dt/2 and of one with the other transfer;
    with ``truth`` ({name: value}) also the truth and the error (``|dlog10|`` for log10-fitted
    parameters, else ``|d|`` in the parameter's unit).
    """
    rows = [("parameter", "initial", "estimate", "std") + tuple(header for _, header in numerics_columns(result.numerics))
            + (("truth", "error") if truth else ())]
    for name, value in result.values.items():
        row = (name, format_value(result.initial.get(name)), format_value(value), format_value(result.std.get(name)))
        row += numerics_cells(result.numerics, name)
        if truth:
            row += (format_value(truth[name]), _error_text(name, value, truth[name]))
        rows.append(row)
    return "\n".join(aligned(rows, rule=True))


def format_timing(result) -> str:
    """Where a fit's time went (``result.timing`` and each stage's ``timing``), as a text table."""
    t = result.timing
    lines = [f"time: {t['total_s']:.1f} s in all; planning (contact detection) {t['planning_s']:.1f} s, "
             f"solvers {t['solver_s']:.1f} s (compilation ~{t['compile_s']:.1f} s), "
             f"uncertainty {t['uncertainty_s']:.1f} s"
             + (f", numerics check {t['numerics_s']:.1f} s" if t.get("numerics_s") else "")
             + (f", velocity polish {t['polish_s']:.1f} s" if t.get("polish_s") else "")]
    rows = [("stage", "iterations", "start", "median step", "all steps", "checks", "rejected", "std")]
    for k, st in enumerate(result.stages, 1):
        g = st.get("timing", {})
        rows.append((f"{k} {st['label'][:28]}", str(st["iterations"]), f"{g.get('start_s', 0):.2f}",
                     f"{g.get('step_s', 0):.3f}", f"{g.get('steps_s', 0):.2f}", f"{g.get('checks_s', 0):.2f}",
                     str(g.get("rejected_steps", "-")), f"{g.get('uncertainty_s', 0):.2f}"))
    return "\n".join(lines + aligned(rows))


def format_value(v) -> str:
    """A parameter value for tables: ``-`` for None, 4 significant digits, vectors in brackets."""
    if v is None:
        return "-"
    v = np.asarray(v, float)
    if v.ndim:
        return "[" + ", ".join(f"{x:.4g}" for x in v) + "]"
    return f"{float(v):.4g}"


def _error_text(name, value, truth) -> str:
    from .identify.parameters import transform_of
    from .parameters import Log10

    value, truth = np.asarray(value, float), np.asarray(truth, float)
    if isinstance(transform_of(name), Log10):
        return f"|dlog10| = {float(np.max(np.abs(np.log10(value) - np.log10(truth)))):.4f}"
    return f"|d| = {float(np.max(np.abs(value - truth))):.4g}"

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


def format_table(result, truth: dict | None = None) -> str:
    """The parameters of a :class:`~jaxmpm.fit.FitResult` as an aligned text table.

    Columns: parameter, initial, estimate, std; with ``truth`` ({name: value}) also the truth and
    the error (``|dlog10|`` for log10-fitted parameters, else ``|d|`` in the parameter's unit).
    """
    rows = [("parameter", "initial", "estimate", "std") + (("truth", "error") if truth else ())]
    for name, value in result.values.items():
        row = (name, _fmt(result.initial.get(name)), _fmt(value), _fmt(result.std.get(name)))
        if truth:
            row += (_fmt(truth[name]), _error_text(name, value, truth[name]))
        rows.append(row)
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)) for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def _fmt(v) -> str:
    if v is None:
        return "-"
    v = np.asarray(v, float)
    if v.ndim:
        return "[" + ", ".join(f"{x:.4g}" for x in v) + "]"
    return f"{float(v):.4g}"


def _error_text(name, value, truth) -> str:
    from .fit import LOG10_PARAMS, _leaf

    value, truth = np.asarray(value, float), np.asarray(truth, float)
    if _leaf(name) in LOG10_PARAMS:
        return f"|dlog10| = {float(np.max(np.abs(np.log10(value) - np.log10(truth)))):.4f}"
    return f"|d| = {float(np.max(np.abs(value - truth))):.4g}"

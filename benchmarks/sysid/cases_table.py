"""Per-case markdown table of a sysid benchmark run (one row per identification).

    python benchmarks/sysid/cases_table.py benchmarks/sysid/results/reduced/results.jsonl

Columns: the case, particles, each fitted parameter's truth -> estimate and error
(|Δlog10| for μ κ τ_Y η E, |Δ| for ν and φ in degrees), the initial-velocity error, whether
every stage converged, LM iterations, wall and CPU seconds of the identification (ground
truth generation excluded), the 1-minute load average at its end, the peak RSS of the
case's process and the commit it ran on (``–`` for rows from before session 4, which did
not record it; docs/benchmark_sysid.md names their commits). The grouped summary (mean ± std) is ``OUT/table.md`` from the runner.
"""

from __future__ import annotations

import json
import sys

from jaxmpm.bench_sysid import LINEAR, PARAM_HEADERS


def _num(v: float) -> str:
    return f"{v:.3g}" if v < 1e3 or v >= 1e5 else f"{v:.0f}"


def main(path: str) -> None:
    rows = [json.loads(line) for line in open(path) if line.strip()]
    head = ["case", "particles", "parameters: truth → estimate (error)", "‖Δv‖ m/s", "conv.", "iter.", "wall s",
            "CPU s", "load", "peak MB", "code"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        if "error" in r:
            print(f"| `{r['key']}` | – | failed: {r['error']} | | | | | | | {r.get('peak_rss_mb', 0):.0f} | {r.get('code', '–')} |")
            continue
        params = []
        for name, err in r["errors"].items():
            est = float(r["estimate"][name] if not isinstance(r["estimate"][name], list) else r["estimate"][name][0])
            unit = "Δ" if name in LINEAR else "Δlog10"
            params.append(f"{PARAM_HEADERS[name]}: {_num(r['truth'][name])} → {_num(est)} ({unit} {err:.2g})")
        print(f"| `{r['key']}` | {r['particles']} | {'; '.join(params)} | {r['velocity_error']:.2g} | "
              f"{'yes' if r['converged'] else 'no'} | {r['iterations']} | {r['seconds']:.0f} | "
              f"{r['cpu_seconds']:.0f} | {r['load_average']:.1f} | {r['peak_rss_mb']:.0f} | {r.get('code', '–')} |")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "benchmarks/sysid/results/reduced/results.jsonl")

"""Where two nearby parameter values of a sysid case part ways: the substeps at which CPIC's
discrete decisions differ between their rollouts.

A case of ``jaxmpm bench sysid`` (``--case``) is simulated twice, with the log10 parameter
``--name`` moved from its true value by each of the two ``--offsets`` (decades), stepping both
rollouts together. At every substep where a discrete field of CPIC's :class:`~jaxmpm.cpic.Contact`
(the persistent side tags, the incompatible and owned node bits) differs between them, or the
largest position difference grows more than threefold, the substep, that difference and the
first particles concerned are printed (up to ``--report`` substeps). On a smooth model the
positions part as the derivative predicts; where a decision differs, they part at once.

    python benchmarks/sysid_first_jump.py --case newtonian-small-0-tracks-cpic --name mu \\
        --offsets=-2e-6,-4e-6 --float64 [--substeps 600] [--report 12]
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--case", default="newtonian-small-0-tracks-cpic")
    parser.add_argument("--preset", default="reduced", choices=("ci", "reduced", "full"))
    parser.add_argument("--name", default="mu", help="a log10 parameter of the case's material")
    parser.add_argument("--offsets", default="-2e-6,-4e-6", help="two offsets from the truth, decades")
    parser.add_argument("--substeps", type=int, default=None, help="how many substeps (default: the whole rollout)")
    parser.add_argument("--report", type=int, default=12, help="stop after this many reported substeps")
    parser.add_argument("--float64", action="store_true")
    args = parser.parse_args(argv)
    offsets = [float(v) for v in args.offsets.split(",")]
    if len(offsets) != 2:
        parser.error("--offsets takes two values")

    import jax

    if args.float64:
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from jaxmpm.bench_sysid import truth_scene
    from jaxmpm.identify.parameters import with_values
    from jaxmpm.model import initial_state
    from jaxmpm.state import compute_stencil
    from jaxmpm.step import gather_contact, step

    try:
        scene, case, truth = truth_scene(args.case, args.preset, jnp.float64 if args.float64 else jnp.float32)
    except ValueError as err:
        parser.error(str(err))
    if case.mode != "cpic":
        parser.error("the case must use CPIC (its decisions are what this compares)")
    if args.name not in truth:
        parser.error(f"--name must be one of {sorted(truth)}")
    model = scene.model

    @jax.jit
    def advance(params, state):
        contact = gather_contact(model, compute_stencil(model.grid, state.x), state)
        return step(model, params, state), contact

    params = [with_values(model, scene.params, {args.name: truth[args.name] * 10.0**d}) for d in offsets]
    states = [initial_state(model, p) for p in params]
    total = args.substeps or (model.frames - 1) * model.substeps
    previous, reported = 0.0, 0
    for i in range(total):
        (a, ca), (b, cb) = (advance(p, s) for p, s in zip(params, states))
        differing = {}
        if ca is not None:
            for field in ("tag", "incompatible", "owned"):
                fa, fb = getattr(ca, field), getattr(cb, field)
                fa = np.asarray(jnp.stack(fa, -1) if isinstance(fa, tuple) else fa)
                fb = np.asarray(jnp.stack(fb, -1) if isinstance(fb, tuple) else fb)
                rows = np.nonzero((fa != fb).reshape(fa.shape[0], -1).any(-1))[0]
                if rows.size:
                    differing[field] = rows
        gap = float(np.max(np.abs(np.asarray(a.x - b.x))))
        if differing or gap > 3.0 * previous + 1e-12:
            reported += 1
            print(f"substep {i} (frame {i / model.substeps:.2f}): positions differ by up to {gap:.3e} m "
                  f"(before: {previous:.3e})" + ("" if differing else "; no discrete decision differs"))
            for field, rows in differing.items():
                shown = ", ".join(
                    f"#{r} (phi {float(ca.phi[0][r]):+.4e} / {float(cb.phi[0][r]):+.4e} m)" for r in rows[:4])
                print(f"    {field} differs for {rows.size} particle(s): {shown}")
            if reported >= args.report:
                break
        previous = max(gap, 1e-300)
        states = [a, b]
    return 0


if __name__ == "__main__":
    sys.exit(main())

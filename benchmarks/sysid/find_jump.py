"""Where does a fit's loss jump between two nearby parameter points? (issue 15, session 19)

    PYTHONPATH=. python benchmarks/sysid/find_jump.py --case viscoplastic-bunny-0-tracks-cpic \
        --a '{"eta": 9.42, "kappa": 106150, "mu": 2266.0, "yield_stress": 525.5}' \
        --b '{"eta": 9.41, "kappa": 106130, "mu": 2266.4, "yield_stress": 525.9}' \
        --velocity=-2.727e-5,-0.99994540,9.141e-6

Rolls the reduced preset's scene of ``--case`` out at both points, substep by substep, and
stops at the first substep whose particle velocities differ by more than ``--ratio`` times the
substep before (a jump, not the smooth growth of a parameter change). There it tells whether
the step is discontinuous in the parameters (the same state stepped with either) or in the
state (the two states stepped with the same parameters), and, for the state, bisects the
segment between the two states to the switch and prints the particle's CPIC quantities on
either side of it (stencil base, signed distance, normal, incompatible bits) and those of the
particle whose contact changed most there. Where the velocity moves steadily along the segment
(sampled at 65 points first: no step above a quarter of the whole), the response is steep but
continuous, as a contact's position correction gives: it says so and goes on. ``--not-thin``
rolls out with every thin collision field treated as a thick one.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import json

import equinox as eqx
import jax
import numpy as np

from jaxmpm.bench_sysid import preset_cases, scene_spec
from jaxmpm.scene import load_scene
from jaxmpm.state import compute_stencil

sim = importlib.import_module("jaxmpm.step")


def _setup(case, preset, values: dict, velocity, not_thin: bool = False):
    scene = load_scene(scene_spec(case, preset, values, velocity=velocity))
    model = scene.model
    if not_thin:  # every field as a thick one: side bits only, no opposed-node test
        model = dataclasses.replace(model, fields=tuple(
            None if f is None else dataclasses.replace(f, thin=False) for f in model.fields))
    model, params, state = sim._start(model, scene.params, None)
    return model, params, state, jax.jit(lambda s: sim.step(model, params, s))


def _contact(model, state, i):
    st = compute_stencil(model.grid, state.x)
    c = sim.gather_contact(model, st, state)
    out = {"base": np.asarray(st.base[i]).tolist()}
    for k in range(0 if c is None else len(c.index)):
        out[f"collider {c.index[k]}"] = {"phi": float(c.phi[k][i]), "normal": np.round(np.asarray(c.normal[k][i]), 5).tolist(),
                                         "incompatible bits": int(c.incompatible[k][i]), "tag": int(c.tag[i, c.index[k]])}
    return out


def _most_changed(model, state_a, state_b) -> int:
    """The particle whose contact data (signed distance, tag, bits) differ most between two
    states."""
    ca, cb = (sim.gather_contact(model, compute_stencil(model.grid, s.x), s) for s in (state_a, state_b))
    change = np.zeros(state_a.x.shape[0])
    for k in range(0 if ca is None else len(ca.index)):
        change += np.abs(np.asarray(ca.phi[k] - cb.phi[k])) / model.grid.dx
        change += np.asarray(ca.incompatible[k] != cb.incompatible[k]) + np.asarray(ca.tag != cb.tag).any(axis=1)
    return int(change.argmax())


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--case", required=True)
    ap.add_argument("--preset", default="reduced")
    ap.add_argument("--a", required=True, help="JSON of the material values at the first point")
    ap.add_argument("--b", required=True, help="... and at the second")
    ap.add_argument("--velocity", default="0,-1,0", help="initial velocity, m/s (both points)")
    ap.add_argument("--ratio", type=float, default=20.0)
    ap.add_argument("--not-thin", action="store_true",
                    help="treat thin collision fields as thick ones (is their opposed-node test the jump?)")
    args = ap.parse_args(argv)
    preset, cases = preset_cases(args.preset)
    case = next(c for c in cases if c.key == args.case)
    velocity = tuple(float(v) for v in args.velocity.split(","))
    ma, _, sa, fa = _setup(case, preset, json.loads(args.a), velocity, args.not_thin)
    _, _, sb, fb = _setup(case, preset, json.loads(args.b), velocity, args.not_thin)
    prev = 0.0
    for k in range(ma.frames * ma.substeps):
        na, nb = fa(sa), fb(sb)
        dv = np.linalg.norm(np.asarray(na.v - nb.v), axis=1)
        if dv.max() > args.ratio * max(prev, 1e-6) and dv.max() > 1e-4:
            i = int(dv.argmax())
            in_params = float(np.linalg.norm(np.asarray(fb(sa).v[i] - na.v[i])))
            in_state = float(np.linalg.norm(np.asarray(fa(sb).v[i] - na.v[i])))
            print(f"substep {k} (frame {k / ma.substeps:.2f}): largest velocity difference {dv.max():.3e} m/s "
                  f"(substep before: {prev:.3e}) at particle {i}, x = {np.round(np.asarray(sa.x[i]), 4).tolist()}")
            print(f"  the same state stepped with the other parameters: {in_params:.3e} m/s; "
                  f"the other state with the same parameters: {in_state:.3e} m/s")

            def at(t):
                return eqx.tree_at(lambda s: s.x, sa, sa.x + t * (sb.x - sa.x))

            profile = np.stack([np.asarray(fa(at(t)).v[i]) for t in np.linspace(0.0, 1.0, 65)])
            largest = float(np.linalg.norm(np.diff(profile, axis=0), axis=1).max())
            if largest < 0.25 * in_state:  # no step: the velocity moves along the segment in small ones
                print(f"  continuous: along the segment in 64 steps the velocity moves by at most {largest:.3e} "
                      f"m/s per step; a steep but smooth response, going on")
                prev = dv.max()
                sa, sb = na, nb
                continue
            lo, hi = 0.0, 1.0
            v_lo = profile[0]
            for _ in range(40):
                mid = 0.5 * (lo + hi)
                if np.linalg.norm(np.asarray(fa(at(mid)).v[i]) - v_lo) < 0.5 * in_state:
                    lo = mid
                else:
                    hi = mid
            print(f"  switch between t = {lo:.12f} and {hi:.12f} of the segment between the two states")
            print(f"  before: {_contact(ma, at(lo), i)}")
            print(f"  after:  {_contact(ma, at(hi), i)}")
            j = _most_changed(ma, at(lo), at(hi))
            if j != i:
                print(f"  the particle whose contact changed most there: {j}")
                print(f"  before: {_contact(ma, at(lo), j)}")
                print(f"  after:  {_contact(ma, at(hi), j)}")
            return
        prev = dv.max()
        sa, sb = na, nb
    print("no jump found")


if __name__ == "__main__":
    main()

"""How a CPIC box's ``restitution`` acts on what lands on it (docs/colliders.md, "Restitution in
CPIC"): one free particle and an elastic disk thrown at 2 m/s onto a slip box (2D, dx = 0.02 m,
no gravity), its top on a node row and half a cell above one, against the grid-level plane.

Per case it prints the arrival speed (the body's mean normal speed when its lowest particle is
still two cells above the face, before the ghost layer acts), the rebound (the largest mean upward
speed afterwards), their ratio, and where the lowest particle came closest to the face (in
cells; negative: inside). ``python benchmarks/cpic_restitution.py [--out FILE.jsonl]``.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import tempfile

import jax
import numpy as np

from jaxmpm import load_scene, simulate

DX = 0.02
SPEED = 2.0


def spec(body: str, collider: str, top: float, restitution: float, E: float) -> dict:
    material = {"model": "elastic", "E": E, "nu": 0.3}
    if body == "particle":
        folder = pathlib.Path(tempfile.mkdtemp())
        np.save(folder / "one.npy", np.array([[0.5, top + 3.0 * DX]]))
        shape = {"shape": "points", "path": str(folder / "one.npy")}
    else:  # a disk of radius 8 cm, its lowest point 3 cells above the face
        shape = {"shape": "sphere", "center": [0.5, top + 3.0 * DX + 0.08], "radius": 0.08}
    if collider == "box":
        geometry = {"type": "box", "lo": [0.0, 0.0], "hi": [1.0, top]}
    else:
        geometry = {"type": "plane", "point": [0.0, top], "normal": [0.0, 1.0]}
    return {
        "dim": 2, "dx": DX, "domain": {"lo": [0, 0], "hi": [1, 1]}, "frames": 60, "frame_dt": 1 / 480,
        "substeps": 8, "gravity": [0.0, 0.0],
        "bodies": [{**shape, "velocity": [0.0, -SPEED], "material": material}],
        "colliders": [{**geometry, "name": "floor", "contact": "slip", "restitution": restitution}],
    }


def measure(body: str, collider: str, top: float, restitution: float, E: float) -> dict:
    scene = load_scene(spec(body, collider, top, restitution, E))
    traj = jax.jit(lambda p: simulate(scene.model, p, checkpoint=None))(scene.params)
    y, vy = np.asarray(traj.x)[..., 1], np.asarray(traj.v)[..., 1].mean(axis=1)
    gap = (y.min(axis=1) - top) / DX  # the lowest particle's height above the face, cells
    before = int(np.argmax(gap < 2.0))
    arrival = -vy[before]
    rebound = max(float(vy[before:].max()), 0.0)
    return {"body": body, "collider": collider, "top_cells": round(top / DX, 3), "restitution": restitution,
            "E": E, "arrival": float(arrival), "rebound": rebound, "ratio": rebound / float(arrival),
            "closest_cells": float(gap.min()), "final_vy": float(vy[-1])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", help="also write the rows to this JSON-lines file")
    args = parser.parse_args()
    cases = [("particle", "box", top, e, E) for E in (1.0, 1e3) for top in (0.1, 0.11) for e in (0.0, 0.5, 1.0)]
    cases += [("disk", kind, top, e, 3e4) for kind in ("box", "plane") for top in (0.1, 0.11) for e in (0.0, 0.5, 1.0)]
    rows = []
    print(f"{'body':9}{'collider':9}{'top/dx':>7}{'e':>5}{'E Pa':>8}{'arrival':>9}{'rebound':>9}{'ratio':>7}"
          f"{'closest/dx':>11}")
    for case in cases:
        r = measure(*case)
        rows.append(r)
        print(f"{r['body']:9}{r['collider']:9}{r['top_cells']:>7}{r['restitution']:>5}{r['E']:>8.0f}"
              f"{r['arrival']:>9.3f}{r['rebound']:>9.3f}{r['ratio']:>7.2f}{r['closest_cells']:>11.3f}", flush=True)
    if args.out:
        with open(args.out, "w") as f:
            f.writelines(json.dumps(r) + "\n" for r in rows)


if __name__ == "__main__":
    main()

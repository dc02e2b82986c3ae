"""Op profiles of two forward-mode programs (k tangents of the parameters and the state, a
10-step rollout of the 25,000-particle cube) traced in alternation in one process (session 53),
summed per XLA op over ROUNDS rounds; prints the ops whose CPU ms differ most from the
per-direction scaling k_a / k_b.

    python benchmarks/results/grad_s53/profile_pair.py KA,KB ROUNDS OUT.json
"""
import sys, collections, tempfile, json, numpy as np, jax
from tangent_program import P, push, arguments
ks = [int(a) for a in sys.argv[1].split(",")]
tabs = {k: collections.defaultdict(float) for k in ks}
walls = {k: [] for k in ks}
for r in range(int(sys.argv[2])):
    for k in (ks if r % 2 == 0 else ks[::-1]):
        params, dynamic, tangents = arguments(k)
        t, w, c = P.profile(push, (params, dynamic, tangents), 3, 10)
        walls[k].append(w)
        for op, v in t.items(): tabs[k][op] += v["ms"]
        for op, v in t.items(): tabs[k]["@name:" + op] = v["op_name"]
import json
json.dump({str(k): dict(v) for k, v in tabs.items()}, open(sys.argv[3], "w"))
print({k: [round(x, 1) for x in w] for k, w in walls.items()})
a, b = ks
rows = []
for op in tabs[a]:
    if op.startswith("@"): continue
    x, y = tabs[a][op], tabs[b].get(op, 0.0)
    rows.append((x - y * a / b, x, y, op, tabs[a]["@name:" + op]))
rows.sort(reverse=True)
print(f"op | k={a} | k={b} | k={a} - {a}/{b} k={b}")
for d, x, y, op, n in rows[:30]:
    print(f"{op} | {x:.2f} | {y:.2f} | {d:.2f} | {n[-70:]}")
print("total", sum(r[1] for r in rows), sum(r[2] for r in rows))

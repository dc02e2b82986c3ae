"""Split a forward-mode op profile into batched ops (a leading axis of k tangents) and unbatched
ones (the primal plus the rules' primal-only work), per stage (session 53).

    taskset -c 0 python benchmarks/profile_step.py --particles 25000 --grid 64 --steps 10 \
        --repeats 3 --tangents 2 --json profile_1core_k2.json
    python benchmarks/results/grad_s53/split_batched.py profile_1core_k2.json 2

It compiles the same k-tangent program as profile_step.py to read each op's output shape."""
import collections, json, re, sys
sys.path.insert(0, "benchmarks")
import jax
import profile_step as P

path, k = sys.argv[1], int(sys.argv[2])
texts = []


def capture(fn, args, repeats, steps=1):
    texts.append(jax.jit(fn).lower(*args).compile().as_text())
    return {}, 1.0, 1.0


P.profile = capture
try:
    P.main(["--steps", "10", "--repeats", "1", "--tangents", str(k)])
except ZeroDivisionError:  # its report of the empty profiles; the programs are captured
    pass
shape = {}
for m in re.finditer(r"^\s*(?:ROOT\s+)?%([\w.\-]+) = (\S+?)\{?[\d,]*\}? ", texts[-1], re.M):
    shape.setdefault(m.group(1), m.group(2))
prof = json.load(open(path))


def stage(op_name):
    m = re.search(r"closed_call/(\w+)", op_name)
    return m.group(1) if m else "outside"


forward, unbatched, batched = (collections.defaultdict(float) for _ in range(3))
for op, v in prof["forward"].items():
    forward[stage(v["op_name"])] += v["ms"]
for op, v in prof["jvp"].items():
    s = shape.get(op, "?")
    lead = re.match(r"\w+\[(\d+)[,\]]", s)
    # a leading axis of k, or k folded into the particle, stencil-row or node axis (the
    # scatter's batching rule): 25,000 particles, 3^3 or 9 rows per particle, 67^3 nodes
    folded = lead and int(lead.group(1)) in {k * n for n in (25000, 27 * 25000, 9 * 25000, 67**3)}
    (batched if re.match(rf"\w+\[{k},", s) or folded else unbatched)[stage(v["op_name"])] += v["ms"]
print(f"CPU ms per step | forward | jvp, unbatched ops | jvp, batched ops ({k} directions)")
for st in sorted(set(forward) | set(unbatched) | set(batched)):
    print(f"{st:12s} {forward[st]:7.2f} {unbatched[st]:7.2f} {batched[st]:7.2f}")
print(f"{'total':12s} {sum(forward.values()):7.2f} {sum(unbatched.values()):7.2f} {sum(batched.values()):7.2f}")

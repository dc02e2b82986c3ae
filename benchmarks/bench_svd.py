"""Benchmark jaxmpm's batched 3x3 SVD against jnp.linalg.svd (jitted, CPU by default).

Times, after warm-up, the median of several runs (with ``block_until_ready``) of

* the forward decomposition of N matrices, and
* forward + backward of a Hencky-energy sum ``sum(mu |log s|^2 + lam/2 (sum log s)^2)``
  (needs only d sigma), and
* forward + backward of a contraction of the Hencky Kirchhoff stress
  ``tau = U diag(2 mu log s + lam sum log s) U^T`` (needs dU as well),

for ``jaxmpm.constitutive.svd.svd`` and ``jnp.linalg.svd``, and prints a table.

Usage: python benchmarks/bench_svd.py [--n 25000] [--dim 3] [--dtype float32] [--repeats 20]
"""

from __future__ import annotations

import argparse
import importlib
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

MU, LAM = 1.0, 1.0


def _hencky(sigma):
    e = jnp.log(jnp.abs(sigma))
    return jnp.sum(MU * jnp.sum(e * e, axis=-1) + 0.5 * LAM * jnp.sum(e, axis=-1) ** 2)


def _kirchhoff_contraction(U, sigma):
    """sum over matrices of <W, U diag(2 mu log s + lam sum log s) U^T> (uses U too)."""
    e = jnp.log(jnp.abs(sigma))
    h = 2 * MU * e + LAM * jnp.sum(e, axis=-1, keepdims=True)
    tau = jnp.einsum("...ij,...j,...kj->...ik", U, h, U)
    w = jnp.arange(1, tau.shape[-1] ** 2 + 1, dtype=tau.dtype).reshape(tau.shape[-2:])
    return jnp.sum(tau * w)


def _time(fn, x, repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(x))  # compile + first run
    compile_s = time.perf_counter() - t0
    for _ in range(2):
        jax.block_until_ready(fn(x))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(x))
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), float(np.min(times)), compile_s


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=25_000, help="number of matrices")
    parser.add_argument("--dim", type=int, default=3, choices=(2, 3))
    parser.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    svd = importlib.import_module("jaxmpm.constitutive.svd").svd

    rng = np.random.default_rng(0)
    d = args.dim
    F = (np.eye(d) + 0.2 * rng.normal(size=(args.n, d, d))).astype(args.dtype)
    F = jax.device_put(F)

    ours_fwd = jax.jit(svd)
    ref_fwd = jax.jit(lambda F: jnp.linalg.svd(F))
    ours_grad = jax.jit(jax.grad(lambda F: _hencky(svd(F)[1])))
    ref_grad = jax.jit(jax.grad(lambda F: _hencky(jnp.linalg.svd(F)[1])))
    ours_tau = jax.jit(jax.grad(lambda F: _kirchhoff_contraction(*svd(F)[:2])))
    ref_tau = jax.jit(jax.grad(lambda F: _kirchhoff_contraction(*jnp.linalg.svd(F)[:2])))

    rows = []
    for name, fn in (
        ("forward    jaxmpm svd", ours_fwd),
        ("forward    jnp.linalg.svd", ref_fwd),
        ("fwd+bwd    jaxmpm svd", ours_grad),
        ("fwd+bwd    jnp.linalg.svd", ref_grad),
        ("fwd+bwd tau jaxmpm svd", ours_tau),
        ("fwd+bwd tau jnp.linalg.svd", ref_tau),
    ):
        med, best, comp = _time(fn, F, args.repeats)
        rows.append((name, med, best, comp))

    # Agreement check (after timing, so that the first-call column includes compilation).
    s_ours = np.abs(np.asarray(ours_fwd(F)[1], np.float64))
    s_ref = np.asarray(ref_fwd(F)[1], np.float64)
    g_ours = np.asarray(ours_grad(F), np.float64)
    g_ref = np.asarray(ref_grad(F), np.float64)
    s_err = np.max(np.abs(s_ours - s_ref) / s_ref[:, :1])
    g_err = np.linalg.norm(g_ours - g_ref) / np.linalg.norm(g_ref)
    t_ours = np.asarray(ours_tau(F), np.float64)
    t_ref = np.asarray(ref_tau(F), np.float64)
    t_err = np.linalg.norm(t_ours - t_ref) / np.linalg.norm(t_ref)

    print(
        f"SVD of {args.n} {d}x{d} {args.dtype} matrices, device {jax.devices()[0].device_kind}, "
        f"({os.cpu_count()} CPUs visible), median of {args.repeats} runs"
    )
    print(f"{'case':30s} {'median ms':>10s} {'min ms':>10s} {'1st call s':>10s} {'speed-up':>9s}")
    for i, (name, med, best, comp) in enumerate(rows):
        ref_med = rows[i | 1][1]
        print(f"{name:30s} {1e3 * med:10.2f} {1e3 * best:10.2f} {comp:10.2f} {ref_med / med:8.1f}x")
    print(
        f"vs jnp.linalg.svd: max |sigma| deviation / sigma_1 {s_err:.1e}; gradient rel. diff: "
        f"Hencky {g_err:.1e}, tau {t_err:.1e}"
    )


if __name__ == "__main__":
    main()

"""Parameter sweeps: many parameter sets at once with ``jax.vmap``, sharded over devices.

::

    out = jaxmpm.sweep(model, params, {"mu": [1.0, 10.0, 100.0]},
                       fn=lambda traj: traj.x[-1, :, 0].max())   # (3,) front positions

The batch of parameter sets is padded to a multiple of the device count and laid out over
all devices (or the ``devices`` given) with a :class:`jax.sharding.NamedSharding` on a 1-D
mesh, so each device simulates its share; the results come back in the order of the sets
with the padding removed. On a CPU, ``XLA_FLAGS=--xla_force_host_platform_device_count=K``
(set before jax is imported) splits the host into K devices.
"""

from __future__ import annotations

import itertools
from typing import Any, Callable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .errors import JaxmpmError
from .identify.parameters import check_varied, get_param, resolve_name, set_param
from .model import Model, Params
from .step import Trajectory, simulate

__all__ = ["sweep", "sweep_params"]

AXIS = "batch"


def sweep_params(
    model: Model, params: Params, overrides: Mapping[str, Any], *, product: bool = False
) -> tuple[dict[str, np.ndarray], int]:
    """The batch of override values by name, ``{name: (B, *shape)}``, and B.

    Arguments:
        overrides: ``{name: values}``; values is a sequence of B values of the parameter's
            shape (scalars for ``mu``, D-vectors for ``velocity``). All names must give the
            same B unless ``product``.
        product: take the Cartesian product of the names' values instead of zipping them.
    """
    if not overrides:
        raise JaxmpmError("sweep needs at least one parameter to vary in 'overrides'")
    check_varied(model, {name: resolve_name(model, params, name) for name in overrides}, "swept")
    values = {}
    for name, vals in overrides.items():
        path = resolve_name(model, params, name)
        leaf = np.asarray(get_param(params, path))
        arr = np.asarray(vals, dtype=leaf.dtype if np.issubdtype(leaf.dtype, np.floating) else float)
        if arr.shape[1:] != leaf.shape:
            if leaf.shape == () and arr.ndim == 0:
                arr = arr[None]
            else:
                raise JaxmpmError(
                    f"sweep values of {name!r} must have shape (B,) + {leaf.shape} (one value per set), got {arr.shape}"
                )
        if len(arr) == 0:
            raise JaxmpmError(f"sweep values of {name!r} are empty")
        if not np.all(np.isfinite(arr)):
            raise JaxmpmError(f"sweep values of {name!r} must be finite")
        values[name] = arr
    if product:
        names = list(values)
        idx = np.array(list(itertools.product(*[range(len(values[n])) for n in names])))
        values = {n: values[n][idx[:, i]] for i, n in enumerate(names)}
    sizes = {n: len(v) for n, v in values.items()}
    if len(set(sizes.values())) != 1:
        raise JaxmpmError(f"sweep values must all have the same length (or pass product=True), got {sizes}")
    return values, next(iter(sizes.values()))


def _default_fn(traj: Trajectory):
    return traj.x


def sweep(
    model: Model,
    params: Params,
    overrides: Mapping[str, Any],
    fn: Callable[[Trajectory], Any] | None = None,
    *,
    product: bool = False,
    devices: Sequence[jax.Device] | None = None,
    batch_size: int | None = None,
    frames: int | None = None,
    observe: Callable | None = None,
    checkpoint: str | None = None,
    with_params: bool = False,
) -> Any:
    """Run the model for many parameter sets at once and return ``fn`` of each rollout.

    Arguments:
        model: the static model.
        params: the base parameter pytree; the ``overrides`` replace its named leaves.
        overrides: ``{name: values}`` (see :func:`sweep_params`), e.g. ``{"mu": [1, 10]}``.
        fn: ``fn(trajectory) -> pytree`` of arrays, evaluated per parameter set inside the
            vmapped, jitted computation (keep its output small: the final positions, a probe
            time series, a loss). Default: the positions ``traj.x`` ``(T, N, D)``. With
            ``with_params=True`` it is called as ``fn(trajectory, params)``.
        product: the Cartesian product of the values instead of zipping them.
        devices: devices to shard the batch over (default: all of ``jax.devices()``).
        batch_size: parameter sets per device per call (bounds memory; default: all at
            once). The batch runs in chunks of ``batch_size × #devices``.
        frames: output frames (default ``model.frames``).
        observe: passed to :func:`~jaxmpm.step.simulate`.
        checkpoint: checkpoint policy (default None: a forward sweep needs none).

    Returns:
        ``fn``'s pytree with a leading batch axis of B (NumPy arrays), in the order of the
        parameter sets.
    """
    values, B = sweep_params(model, params, overrides, product=product)
    fn = _default_fn if fn is None else fn
    devices = list(jax.devices() if devices is None else devices)
    if not devices:
        raise JaxmpmError("sweep needs at least one device")
    n_dev = len(devices)
    mesh = Mesh(np.asarray(devices), (AXIS,))
    batched = NamedSharding(mesh, PartitionSpec(AXIS))
    replicated = NamedSharding(mesh, PartitionSpec())
    paths = {n: resolve_name(model, params, n) for n in values}

    def one(overrides_one, base):
        p = base
        for n, v in overrides_one.items():
            leaf = get_param(base, paths[n])
            p = set_param(p, paths[n], jnp.asarray(v).astype(jnp.asarray(leaf).dtype))
        traj = simulate(model, p, checkpoint=checkpoint, observe=observe, frames=frames)
        return fn(traj, p) if with_params else fn(traj)

    run = jax.jit(jax.vmap(one, in_axes=(0, None)), out_shardings=batched)
    base = jax.device_put(params, replicated)
    per_call = B if batch_size is None else max(1, int(batch_size)) * n_dev
    per_call = -(-per_call // n_dev) * n_dev  # a multiple of the device count
    per_call = min(per_call, -(-B // n_dev) * n_dev)
    outs = []
    for start in range(0, B, per_call):
        chunk = {n: v[start : start + per_call] for n, v in values.items()}
        size = len(next(iter(chunk.values())))
        pad = per_call - size
        if pad:  # repeat the last set; its results are dropped below
            chunk = {n: np.concatenate([v, np.repeat(v[-1:], pad, axis=0)]) for n, v in chunk.items()}
        chunk = jax.device_put(chunk, batched)
        out = run(chunk, base)
        outs.append(jax.tree_util.tree_map(lambda a, size=size: np.asarray(a)[:size], out))
    return jax.tree_util.tree_map(lambda *a: np.concatenate(a), *outs)

"""The abstract material: a return map and a Kirchhoff stress."""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.interpreters import batching
from jaxtyping import Array, Float

from ..errors import SceneError
from ..fusion import lowered_primitive, sum_last, sum_to_shape
from ..parameters import Parameter

Params = dict[str, Float[Array, ""]]

#: Singular values are clamped to at least this before taking logs (PAC-NeRF).
SIGMA_MIN = 0.05
#: Safe-norm epsilon under square roots (PAC-NeRF uses sqrt(x·x + 1e-8)).
NORM_EPS = 1e-8


def safe_norm(x: Float[Array, "... D"], keepdims: bool = False) -> Float[Array, "..."]:
    """``sqrt(x·x + 1e-8)`` over the last axis: finite value and gradient at ``x = 0``."""
    return jnp.sqrt(sum_last(x * x, keepdims=keepdims) + NORM_EPS)


def det(A: Float[Array, "... D D"]) -> Float[Array, "..."]:
    """Determinant of a batch of 2x2 or 3x3 matrices in closed form (fuses on CPU)."""
    if A.shape[-1] == 2:
        return A[..., 0, 0] * A[..., 1, 1] - A[..., 0, 1] * A[..., 1, 0]
    return (
        A[..., 0, 0] * (A[..., 1, 1] * A[..., 2, 2] - A[..., 1, 2] * A[..., 2, 1])
        - A[..., 0, 1] * (A[..., 1, 0] * A[..., 2, 2] - A[..., 1, 2] * A[..., 2, 0])
        + A[..., 0, 2] * (A[..., 1, 0] * A[..., 2, 1] - A[..., 1, 1] * A[..., 2, 0])
    )


def matmul(a: Float[Array, "... I J"], b: Float[Array, "... J K"]) -> Float[Array, "... I K"]:
    """``a @ b`` for batches of small matrices (leading dimensions broadcast), a JAX primitive
    with its own rules so that each mode gets the form XLA's CPU compiler runs fastest:

    - Value and forward mode: ``J`` broadcast products summed elementwise, the tangent
      ``da b + a db`` as two more such products. XLA fuses and vectorises them over the batch;
      its dot op on 3x3 blocks pays a per-block cost (the corotated stress ~1.5x faster), and
      dots on tangents batched by ``jax.vmap`` were slower still (session 24).
    - Reverse mode: the transpose is two dot ops, ``ct b^T`` and ``a^T ct``. The transpose of
      the elementwise form is a sum over a 3-wide axis that XLA runs far slower than a dot:
      with elementwise derivatives everywhere, a 200-step rollout's gradient was 1.5x slower
      (docs/benchmarks.md, session 25). A primitive keeps the two apart (a ``custom_jvp``
      rule is both the forward rule and, transposed, the reverse one).
    - Values are exact float32 or float64 arithmetic at any ``jax_default_matmul_precision``;
      the transpose's dots are at full precision (``Precision.HIGHEST``): JAX may trace them
      after :func:`jaxmpm.precision.full_precision`'s context has closed (under
      ``jax.checkpoint`` in reverse mode).
    """
    dtype = jnp.result_type(a, b)
    return _matmul_p.bind(jnp.asarray(a, dtype), jnp.asarray(b, dtype))


def _matmul_impl(a, b):
    return sum(a[..., :, j, None] * b[..., None, j, :] for j in range(a.shape[-1]))


def _matmul_abstract(a, b):
    batch = jnp.broadcast_shapes(a.shape[:-2], b.shape[:-2])
    return jax.core.ShapedArray((*batch, a.shape[-2], b.shape[-1]), a.dtype)


def _dot(a, b):
    return jnp.matmul(a, b, precision=jax.lax.Precision.HIGHEST)


def _matmul_batch(args, dims):
    size = next(x.shape[d] for x, d in zip(args, dims) if d is not None)
    a, b = (x[None] if d is None else batching.bdim_at_front(x, d, size) for x, d in zip(args, dims))
    a, b = (x.reshape(x.shape[:1] + (1,) * (max(a.ndim, b.ndim) - x.ndim) + x.shape[1:]) for x in (a, b))
    return _matmul_p.bind(a, b), 0


_matmul_p = lowered_primitive(
    "jaxmpm_small_matmul",
    _matmul_impl,
    _matmul_abstract,
    _matmul_batch,
    bilinear=(
        lambda ct, a, b: sum_to_shape(_dot(ct, b.mT), a.aval.shape),
        lambda ct, a, b: sum_to_shape(_dot(a.mT, ct), b.aval.shape),
    ),
)


def lame_from_young(E, nu):
    """Lamé parameters ``(mu, lam)`` from Young's modulus E (Pa) and Poisson ratio nu."""
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam


class Material(eqx.Module):
    """A constitutive model. Concrete materials are final subclasses.

    A material has no array fields: its parameters (in physical units) arrive in a
    dict ``params`` at every call so that they can be differentiated, vmapped and fitted.

    Class attributes:
        name: the scene-file ``model`` string.
        parameters: every parameter of the model, each a :class:`~jaxmpm.parameters.Parameter`
            (units, valid range, fitting space, learning rate, PAC-NeRF's initial guess),
            declared once here, next to the constitutive law that uses it.
        defaults: values of the optional parameters (the others are required).
    """

    name: ClassVar[str]
    parameters: ClassVar[tuple[Parameter, ...]]
    defaults: ClassVar[dict[str, float]] = {}

    @classmethod
    def required(cls) -> tuple[str, ...]:
        """The names a scene must give (PAC-NeRF's fitted parameters of this model)."""
        return tuple(p.name for p in cls.parameters if p.name not in cls.defaults)

    @classmethod
    def parameter_names(cls) -> tuple[str, ...]:
        return tuple(p.name for p in cls.parameters)

    @classmethod
    def parameter(cls, name: str) -> Parameter | None:
        """The declaration of ``name``, or None if this model has no such parameter."""
        return next((p for p in cls.parameters if p.name == name), None)

    @classmethod
    def validate(cls, values: dict[str, float], where: str = "material") -> dict[str, float]:
        """Check names and ranges of user-given parameters; return them with defaults filled."""
        out = dict(cls.defaults)
        for key, value in values.items():
            declared = cls.parameter(key)
            if declared is None:
                raise SceneError(
                    f"{where}: unknown parameter {key!r} for model {cls.name!r} "
                    f"(expected {', '.join(cls.parameter_names())})"
                )
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise SceneError(f"{where}: parameter {key!r} must be a number, got {value!r}") from None
            complaint = declared.check(value, where)
            if complaint is not None:
                raise SceneError(complaint)
            out[key] = value
        for key in cls.required():
            if key not in out:
                raise SceneError(f"{where}: missing required parameter {key!r} for model {cls.name!r}")
        return out

    def init_aux(self, n: int, dtype) -> Float[Array, " N"]:
        """Initial internal scalar per particle (default 0)."""
        return jnp.zeros((n,), dtype)

    @abc.abstractmethod
    def return_map(
        self,
        F_trial: Float[Array, "N D D"],
        C: Float[Array, "N D D"],
        aux: Float[Array, " N"],
        params: Params,
        dt: float,
    ) -> tuple[Float[Array, "N D D"], Float[Array, " N"]]:
        """Project the trial deformation gradient ``(I + dt C) F`` back to the admissible set.

        Returns the new ``F`` and the new internal scalar ``aux``.
        """

    @abc.abstractmethod
    def kirchhoff(
        self,
        F: Float[Array, "N D D"],
        C: Float[Array, "N D D"],
        aux: Float[Array, " N"],
        params: Params,
    ) -> Float[Array, "N D D"]:
        """Kirchhoff stress ``tau = P F^T`` (Pa·m^0, i.e. J times the Cauchy stress)."""

    def update(
        self,
        F_trial: Float[Array, "N D D"],
        C: Float[Array, "N D D"],
        aux: Float[Array, " N"],
        params: Params,
        dt: float,
    ) -> tuple[Float[Array, "N D D"], Float[Array, " N"], Float[Array, "N D D"]]:
        """Return map and the Kirchhoff stress of the projected state, ``(F, aux, tau)``.

        What a step calls. By default :meth:`return_map` then :meth:`kirchhoff`; materials
        whose two halves share work (one SVD for both, see
        :class:`~jaxmpm.constitutive.models.HenckyPlastic`) override it.
        """
        F, aux = self.return_map(F_trial, C, aux, params, dt)
        return F, aux, self.kirchhoff(F, C, aux, params)

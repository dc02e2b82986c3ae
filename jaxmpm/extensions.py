"""The extension library: nested extensions of the base model (DESIGN §5.3 vocabulary).

Every extension is switched on by a key of ``params["extensions"]``::

    params["extensions"] = {
        "drag": {"linear": 0.0, "quadratic": 0.0},
        "gravity": {"delta": jnp.zeros(D)},
        ...
    }

Its parameters are additive offsets whose **null value is zero** and reproduces the base
model (exactly: the same floating-point operations give the same numbers; the only
exception is ``moving_collider``, whose rest-frame look-ups reproduce a static collider up
to float rounding). That holds for each compiled step; in a compiled rollout (``lax.scan``)
XLA may fuse the step differently around an extension's zero term, and ``rate_dependence``
at ``viscosity = 0`` was seen to move the last bit of some velocities (CPU, float32).
Which extensions are present is part of the params pytree's *structure*, so it is static
under ``jit``: an extension that is not in the dict adds no operation to the step.

Where each one acts (see :data:`EXTENSIONS` for parameters, units and bounds):

========================  =================================================================
id                        acts in
========================  =================================================================
``collider_friction``     contact projection: Coulomb ``mu_b`` added to each non-sticky
                          collider's (slip colliders become Coulomb colliders, slip = mu 0)
``restitution``           contact projection: restitution ``e`` added (non-sticky colliders)
``drag``                  grid update: ``v <- v / (1 + dt (k1 + k2 |v|))`` (implicit drag)
``gravity``               grid update: ``g <- g + dg``
``initial_velocity``      initial state: ``v0 <- v0 + dv + w x (x - x_body)``
``moving_collider``       colliders: pivot velocity ``v_c`` added (rigid translation)
``rate_dependence``       stress: extra viscous Kirchhoff stress ``eta J sym(C)``
``cohesion``              sand return map: Drucker–Prager cone shifted by a tensile strength
``heterogeneity``         stress: per-particle factor ``10^(g · xi)``, ``xi`` the reference
                          position scaled to [-1, 1] over the body (scales every stress-like
                          material parameter together: E, mu, kappa, yield stress, eta)
``damping``               G2P: the affine velocity field decays, ``C <- C / (1 + dt zeta)``
``time_offset``           observation: the simulation is compared at ``t - t0``
========================  =================================================================

The step calls the hooks below (:func:`prepare`, :func:`initial_velocity`,
:func:`stress`, :func:`material_update`, :func:`grid_velocity`, :func:`affine`); discovery
code uses :func:`enable`, :func:`parameter_specs`, :func:`flatten` / :func:`unflatten`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import jax.numpy as jnp
import numpy as np

from .colliders.base import row_dot
from .errors import JaxmpmError

__all__ = [
    "EXTENSIONS",
    "ExtensionSpec",
    "ParamSpec",
    "enable",
    "null_params",
    "parameter_specs",
    "applicable",
    "prepare",
]


# --------------------------------------------------------------------------- registry


@dataclass(frozen=True)
class ParamSpec:
    """One parameter of one extension.

    Attributes:
        extension: the extension id.
        key: the key inside ``params["extensions"][extension]``.
        shape: array shape (``()`` or ``(D,)``...).
        lower, upper: bounds of the *offset* (None: unbounded); the null value 0 is inside.
        unit: SI unit, for reports.
        scale: a typical magnitude (for step sizes and reports).
    """

    extension: str
    key: str
    shape: tuple[int, ...]
    lower: float | None
    upper: float | None
    unit: str
    scale: float

    @property
    def name(self) -> str:
        """``"<extension>.<key>"``, the name used in reports."""
        return f"{self.extension}.{self.key}"

    @property
    def size(self) -> int:
        return int(np.prod(self.shape)) if self.shape else 1

    @property
    def bounded(self) -> bool:
        """Whether the null value lies on a bound (one-sided tests apply)."""
        return (self.lower is not None and self.lower == 0.0) or (self.upper is not None and self.upper == 0.0)


@dataclass(frozen=True)
class ExtensionSpec:
    """An extension of the base model: an id, a description and where it acts."""

    id: str
    title: str
    acts_in: str
    signature: str


EXTENSIONS: dict[str, ExtensionSpec] = {
    e.id: e
    for e in (
        ExtensionSpec("collider_friction", "Coulomb friction on the colliders", "contact projection",
                      "tangential error in the contact band during contact; the model slides too far"),
        ExtensionSpec("restitution", "restitution (bounce) at the colliders", "contact projection",
                      "normal-direction error at impact: the observed body bounces back"),
        ExtensionSpec("drag", "air drag (linear and quadratic in speed)", "grid update",
                      "free-flight error growing with speed, deceleration along -v"),
        ExtensionSpec("gravity", "gravity error (magnitude or direction)", "grid update",
                      "free-flight centre-of-mass error growing as t^2"),
        ExtensionSpec("initial_velocity", "initial velocity / spin error", "initial state",
                      "centre-of-mass error growing as t from the start"),
        ExtensionSpec("moving_collider", "a collider moves (rigid translation)", "collider placement",
                      "contact-band error growing with time along the collider motion"),
        ExtensionSpec("rate_dependence", "extra viscous (rate-dependent) stress", "stress",
                      "bulk deformation-rate error: spreads or rebounds too fast"),
        ExtensionSpec("cohesion", "cohesion / tensile strength (sand)", "return map",
                      "observed material stays clumped where the model fragments"),
        ExtensionSpec("heterogeneity", "spatially varying stiffness/strength", "stress",
                      "shape error coherent in the reference configuration"),
        ExtensionSpec("damping", "internal (momentum-conserving) damping", "G2P",
                      "vibrations / spreading die out faster than modelled, COM unaffected"),
        ExtensionSpec("time_offset", "time offset between data and simulation", "observation",
                      "error proportional to the velocity, largest where motion is fastest"),
    )
}


def _rotational_dofs(dim: int) -> int:
    return 1 if dim == 2 else 3


def applicable(model, extension: str) -> str | None:
    """``None`` if ``extension`` applies to ``model``, else the reason it does not."""
    from .constitutive import Sand

    if extension not in EXTENSIONS:
        raise JaxmpmError(f"unknown extension {extension!r}; known: {', '.join(EXTENSIONS)}")
    if extension in ("collider_friction", "restitution") and not _contact_colliders(model):
        return "no slip or friction collider (sticky colliders already stop all sliding and bouncing)"
    if extension == "moving_collider" and not _movable(model):
        return "the scene has no collider that can move"
    if extension == "cohesion" and not any(isinstance(b.material, Sand) for b in model.bodies):
        return "no sand (Drucker-Prager) body"
    return None


def _contact_colliders(model) -> list[int]:
    """Colliders whose contact uses friction and restitution (non-sticky; in the boundary-particle
    mode only planes, since boundary particles are sticky)."""
    from .colliders import Plane

    return [
        k for k, c in enumerate(model.colliders)
        if c.contact != "sticky" and (model.collision != "particles" or isinstance(c, Plane))
    ]


def _movable(model) -> list[int]:
    from .colliders import Plane

    out = []
    for k, c in enumerate(model.colliders):
        if model.collision == "particles" and not isinstance(c, Plane):
            continue
        if not hasattr(c, "pivot"):
            continue
        out.append(k)
    return out


def parameter_specs(model, params, extension: str) -> list[ParamSpec]:
    """The parameters of ``extension`` for this model (per-collider ones are named by collider)."""
    dim = model.dim
    e = extension
    if e == "collider_friction":
        out = []
        for k in _contact_colliders(model):
            c = model.colliders[k]
            base = float(params["colliders"][k]["friction"]) if c.contact == "friction" else 0.0
            out.append(ParamSpec(e, c.name, (), -base, None, "-", 0.1))
        return out
    if e == "restitution":
        out = []
        for k in _contact_colliders(model):
            c = model.colliders[k]
            base = float(params["colliders"][k]["restitution"])
            out.append(ParamSpec(e, c.name, (), -base, 1.0 - base, "-", 0.1))
        return out
    if e == "drag":
        return [ParamSpec(e, "linear", (), 0.0, None, "1/s", 0.1), ParamSpec(e, "quadratic", (), 0.0, None, "1/m", 0.1)]
    if e == "gravity":
        return [ParamSpec(e, "delta", (dim,), None, None, "m/s^2", 0.1)]
    if e == "initial_velocity":
        return [
            ParamSpec(e, "delta", (dim,), None, None, "m/s", 0.1),
            ParamSpec(e, "spin", (_rotational_dofs(dim),), None, None, "rad/s", 0.1),
        ]
    if e == "moving_collider":
        return [ParamSpec(e, model.colliders[k].name, (dim,), None, None, "m/s", 0.1) for k in _movable(model)]
    if e == "rate_dependence":
        return [ParamSpec(e, "viscosity", (), 0.0, None, "Pa s", 1.0)]
    if e == "cohesion":
        return [ParamSpec(e, "strength", (), 0.0, None, "Pa", 100.0)]
    if e == "heterogeneity":
        return [ParamSpec(e, "gradient", (dim,), None, None, "decades", 0.1)]
    if e == "damping":
        return [ParamSpec(e, "rate", (), 0.0, None, "1/s", 0.1)]
    if e == "time_offset":
        return [ParamSpec(e, "t0", (), None, None, "s", 0.01)]
    raise JaxmpmError(f"unknown extension {extension!r}; known: {', '.join(EXTENSIONS)}")


def null_params(model, params, extensions, dtype=None) -> dict[str, dict[str, Any]]:
    """``{id: {key: zeros}}`` for the given extensions (their null values)."""
    dtype = dtype or jnp.asarray(params["gravity"]).dtype
    out = {}
    for e in extensions:
        reason = applicable(model, e)
        if reason is not None:
            raise JaxmpmError(f"extension {e!r} does not apply to this scene: {reason}")
        out[e] = {p.key: jnp.zeros(p.shape, dtype) for p in parameter_specs(model, params, e)}
    return out


def enable(model, params, extensions, values: dict[str, dict] | None = None) -> dict:
    """``params`` with the given extensions switched on at their null values (or ``values``).

    Arguments:
        model: the model.
        params: the base parameter pytree (an existing ``"extensions"`` entry is kept).
        extensions: extension ids.
        values: optional ``{id: {key: value}}`` overriding the null values.
    """
    out = dict(params)
    ext = dict(params.get("extensions") or {})
    ext.update({k: v for k, v in null_params(model, params, extensions).items() if k not in ext})
    dtype = jnp.asarray(params["gravity"]).dtype
    for e, kv in (values or {}).items():
        if e not in ext:
            raise JaxmpmError(f"extension {e!r} is not enabled")
        entry = dict(ext[e])
        for key, value in kv.items():
            if key not in entry:
                raise JaxmpmError(f"extension {e!r} has no parameter {key!r} (has {', '.join(entry)})")
            entry[key] = jnp.broadcast_to(jnp.asarray(value, dtype), jnp.shape(entry[key]))
        ext[e] = entry
    out["extensions"] = ext
    return out


def strip(params) -> dict:
    """``params`` without extensions (the base model)."""
    return {k: v for k, v in params.items() if k != "extensions"}


# --------------------------------------------------------------------------- hooks


def _ext(params) -> dict:
    return params.get("extensions") or {}


def prepare(model, params):
    """Apply the extensions that change the model or the params (called by ``simulate``).

    ``gravity`` (offset to ``params["gravity"]``), ``collider_friction`` / ``restitution``
    (offsets to the collider parameters; slip colliders become Coulomb ones), and
    ``moving_collider`` (each collider gets a rigid motion with the added pivot velocity).
    Returns ``(model, params)``; without extensions both are returned unchanged.
    """
    ext = _ext(params)
    if not ext:
        return model, params
    params = dict(params)
    if "gravity" in ext:
        g = jnp.asarray(params["gravity"])
        params["gravity"] = g + jnp.asarray(ext["gravity"]["delta"]).astype(g.dtype)
    colliders = list(model.colliders)
    cparams = [dict(cp) for cp in params["colliders"]]
    changed = False
    if "collider_friction" in ext:
        for k, c in enumerate(colliders):
            if c.name in ext["collider_friction"]:
                mu = jnp.asarray(cparams[k]["friction"])
                cparams[k]["friction"] = mu + jnp.asarray(ext["collider_friction"][c.name]).astype(mu.dtype)
                if c.contact == "slip":
                    colliders[k] = c.with_contact("friction")
                    changed = True
    if "restitution" in ext:
        for k, c in enumerate(colliders):
            if c.name in ext["restitution"]:
                e = jnp.asarray(cparams[k]["restitution"])
                cparams[k]["restitution"] = e + jnp.asarray(ext["restitution"][c.name]).astype(e.dtype)
    if "moving_collider" in ext:
        for k, c in enumerate(colliders):
            if c.name in ext["moving_collider"]:
                colliders[k] = c.with_contact(motion=_translated_motion(c, ext["moving_collider"][c.name]))
                changed = True
    params["colliders"] = tuple(cparams)
    # consumed: a second call (e.g. a nested simulate) must not apply them again
    params["extensions"] = {k: v for k, v in ext.items() if k not in _PREPARED}
    if changed:
        model = dataclasses.replace(model, colliders=tuple(colliders))  # the same fields: same geometry
    return model, params


#: Extensions applied by :func:`prepare` (removed from the params it returns).
_PREPARED = ("gravity", "collider_friction", "restitution", "moving_collider")


def _translated_motion(collider, dv):
    """A scripted motion = the collider's own rigid motion plus a translation ``dv t``."""
    base_motion = getattr(collider, "motion", None)

    def motion(t):
        if base_motion is not None:
            c, r = base_motion(t)
        else:
            c, r = collider.rigid_transform(t, dtype=t.dtype)
        c = jnp.asarray(c, t.dtype)
        return c + jnp.asarray(dv).astype(t.dtype) * t, jnp.asarray(r, t.dtype)

    return motion


def initial_velocity(model, params, state):
    """Add the ``initial_velocity`` offset ``dv + w x (x - x_body)`` to a fresh state."""
    ext = _ext(params)
    if "initial_velocity" not in ext:
        return state
    import equinox as eqx

    from .colliders import cross_omega

    dtype = state.v.dtype
    dv = jnp.asarray(ext["initial_velocity"]["delta"]).astype(dtype)
    spin = jnp.asarray(ext["initial_velocity"]["spin"]).astype(dtype)
    parts = []
    for sl in model.body_slices():
        x = state.x[sl]
        centre = jnp.mean(x, axis=0)  # the body's centre where it starts (its offset included)
        parts.append(dv + cross_omega(spin, x - centre))
    return eqx.tree_at(lambda s: s.v, state, state.v + jnp.concatenate(parts))


def _reference_coordinates(model, dtype):
    """Reference positions of every particle scaled to [-1, 1] over its body's bounding box."""
    parts = []
    for body in model.bodies:
        x0 = jnp.asarray(body.x0).astype(dtype)
        lo, hi = jnp.min(x0, axis=0), jnp.max(x0, axis=0)
        centre, half = (lo + hi) / 2, jnp.maximum((hi - lo) / 2, 1e-12)
        parts.append((x0 - centre) / half)
    return jnp.concatenate(parts)


def stress(model, params, state, F, aux, tau):
    """Stress hooks after the Kirchhoff stress: ``rate_dependence`` then ``heterogeneity``."""
    ext = _ext(params)
    if "rate_dependence" in ext:
        from .constitutive import Newtonian
        from .constitutive.base import det

        eta = jnp.asarray(ext["rate_dependence"]["viscosity"]).astype(tau.dtype)
        Js = []
        for body, sl in zip(model.bodies, model.body_slices()):
            Js.append(aux[sl] if isinstance(body.material, Newtonian) else det(F[sl]))
        J = jnp.concatenate(Js)[:, None, None]
        C = state.C
        tau = tau + eta * J * 0.5 * (C + jnp.swapaxes(C, -1, -2))
    if "heterogeneity" in ext:
        g = jnp.asarray(ext["heterogeneity"]["gradient"]).astype(tau.dtype)
        xi = _reference_coordinates(model, tau.dtype)
        scale = 10.0 ** row_dot(xi, g)
        tau = tau * scale[:, None, None]
    return tau


def material_update(material, F_trial, C, aux, body_params, dt, params):
    """The body's return map and stress (:meth:`~jaxmpm.constitutive.Material.update`);
    the ``cohesion`` extension gives sand bodies a tensile strength (the ``cohesion`` entry
    of :func:`jaxmpm.constitutive.models.drucker_prager_projection`)."""
    ext = _ext(params)
    from .constitutive import Sand

    if "cohesion" in ext and isinstance(material, Sand):
        body_params = {**body_params, "cohesion": jnp.asarray(ext["cohesion"]["strength"]).astype(F_trial.dtype)}
    return material.update(F_trial, C, aux, body_params, dt)


def grid_velocity(model, params, v):
    """``drag`` on the grid velocities (after gravity, before the collider conditions):
    implicit ``v <- v / (1 + dt (k1 + k2 |v|))``."""
    ext = _ext(params)
    if "drag" not in ext:
        return v
    dt = model.dt
    k1 = jnp.asarray(ext["drag"]["linear"]).astype(v.dtype)
    k2 = jnp.asarray(ext["drag"]["quadratic"]).astype(v.dtype)
    speed = jnp.sqrt(row_dot(v, v, keepdims=True) + 1e-12)  # (unrolled: a reduction over D is slow on CPU)
    return v / (1.0 + dt * (k1 + k2 * speed))


def affine(model, params, C):
    """``damping`` of the particles' affine velocity field after G2P: ``C <- C / (1 + dt zeta)``."""
    ext = _ext(params)
    if "damping" not in ext:
        return C
    zeta = jnp.asarray(ext["damping"]["rate"]).astype(C.dtype)
    return C / (1.0 + model.dt * zeta)


def time_offset(params):
    """The ``time_offset`` t0 (seconds) or None."""
    ext = _ext(params)
    if "time_offset" not in ext:
        return None
    return ext["time_offset"]["t0"]


# --------------------------------------------------------------------------- flat vectors


def flatten(specs: list[ParamSpec], ext: dict) -> np.ndarray:
    """The values of ``specs`` in ``ext`` (``params["extensions"]``) as one flat vector."""
    return np.concatenate([np.ravel(np.asarray(ext[s.extension][s.key], float)) for s in specs]) if specs else np.zeros(0)


def unflatten(specs: list[ParamSpec], flat, ext: dict, dtype) -> dict:
    """``ext`` with the values of ``specs`` taken from ``flat`` (traceable)."""
    out = {k: dict(v) for k, v in ext.items()}
    i = 0
    for s in specs:
        out[s.extension][s.key] = jnp.reshape(flat[i:i + s.size], s.shape).astype(dtype)
        i += s.size
    return out


def describe(extension: str) -> str:
    spec = EXTENSIONS[extension]
    return f"{spec.title} ({spec.acts_in})"

"""Named parameters: where they live in the parameter pytree and the space they are fitted in.

A name is ``"mu"`` (the only body that has it), ``"body1.mu"`` (a given body),
``"floor.friction"`` (a collider's parameter) or ``"gravity"``. What is known about each
parameter (units, range, fitting space, learning rate, initial guess) is declared once, in
:class:`jaxmpm.parameters.Parameter` objects next to its material or owner; this module reads
those declarations by the name's last component.
"""

from __future__ import annotations

from typing import Sequence

import jax.numpy as jnp

from ..constitutive import MATERIALS
from ..errors import JaxmpmError
from ..model import Model, Params, inert_contact_parameter
from ..parameters import BODY_PARAMETERS, COLLIDER_PARAMETERS, GRAVITY, Linear, Log10, Parameter, Transform

__all__ = [
    "leaf_name",
    "declaration",
    "transform_of",
    "resolve_name",
    "get_param",
    "set_param",
    "to_unconstrained",
    "from_unconstrained",
    "apply_unconstrained",
    "default_names",
    "material_name",
    "check_names",
    "check_varied",
    "LOG10_PARAMS",
    "ADAM_LEARNING_RATES",
]


def _declarations() -> dict[str, Parameter]:
    """Every declared parameter by name; a name declared by several owners (``mu``: a
    viscosity and a shear modulus) must be fitted in the same space by all of them."""
    out: dict[str, Parameter] = {GRAVITY.name: GRAVITY, **BODY_PARAMETERS, **COLLIDER_PARAMETERS}
    for material in MATERIALS.values():
        for p in material.parameters:
            seen = out.setdefault(p.name, p)
            if type(seen.transform) is not type(p.transform) or seen.learning_rate != p.learning_rate:
                raise TypeError(f"parameter {p.name!r} is declared with different fitting spaces")
    return out


_DECLARED = _declarations()

#: Names fitted in log10 (PAC-NeRF's space for moduli, viscosities and densities).
LOG10_PARAMS = frozenset(n for n, p in _DECLARED.items() if isinstance(p.transform, Log10))
#: Adam's learning rate of each declared parameter, in its optimisation space.
ADAM_LEARNING_RATES = {n: p.learning_rate for n, p in _DECLARED.items()}


def leaf_name(name: str) -> str:
    """``"body1.mu"`` -> ``"mu"``."""
    return name.rsplit(".", 1)[-1]


def declaration(name: str) -> Parameter | None:
    """The declaration of a (possibly qualified) parameter name, or None (e.g. an extension's)."""
    return _DECLARED.get(leaf_name(name))


def transform_of(name: str) -> Transform:
    """The fitting space of ``name`` (linear for undeclared names)."""
    p = declaration(name)
    return Linear() if p is None else p.transform


def to_unconstrained(name: str, value):
    """Physical value -> optimisation variable (PAC-NeRF's spaces)."""
    return transform_of(name).to_unconstrained(value)


def from_unconstrained(name: str, y):
    """Optimisation variable -> physical value."""
    return transform_of(name).from_unconstrained(y)


def material_name(body) -> str:
    return getattr(type(body.material), "name", type(body.material).__name__)


def resolve_name(model: Model, params: Params, name: str) -> tuple:
    """The path of a named parameter inside ``params`` (see the module docstring)."""
    if not isinstance(name, str) or not name:
        raise JaxmpmError(f"parameter names must be non-empty strings, got {name!r}")
    if name == "gravity":
        return ("gravity",)
    if "." in name:
        owner, leaf = name.split(".", 1)
        for k, body in enumerate(model.bodies):
            if body.name == owner:
                if leaf not in params["bodies"][k]:
                    raise JaxmpmError(
                        f"parameter {name!r}: body {owner!r} ({material_name(body)}) has no parameter {leaf!r}; "
                        f"it has: {', '.join(sorted(params['bodies'][k]))}"
                    )
                return ("bodies", k, leaf)
        for k, collider in enumerate(model.colliders):
            if collider.name == owner:
                if leaf not in params["colliders"][k]:
                    raise JaxmpmError(f"parameter {name!r}: collider {owner!r} has no parameter {leaf!r}; "
                                     f"it has: {', '.join(sorted(params['colliders'][k]))}")
                return ("colliders", k, leaf)
        raise JaxmpmError(f"parameter {name!r}: no body or collider named {owner!r}")
    owners = [k for k, bp in enumerate(params["bodies"]) if name in bp]
    if not owners:
        available = sorted({key for bp in params["bodies"] for key in bp} | {"gravity"})
        available += [f"{c.name}.{key}" for c, cp in zip(model.colliders, params["colliders"]) for key in sorted(cp)]
        materials = ", ".join(sorted({material_name(b) for b in model.bodies}))
        raise JaxmpmError(
            f"unknown parameter {name!r} for this scene's material ({materials}); this scene has: {', '.join(available)}"
        )
    if len(owners) > 1:
        choices = ", ".join(f"{model.bodies[k].name}.{name}" for k in owners)
        raise JaxmpmError(f"parameter {name!r} is ambiguous in a scene with several bodies; use one of {choices}")
    return ("bodies", owners[0], name)


def check_names(names: Sequence[str], where: str = "parameter names") -> list[str]:
    """``names`` as a list, refusing empty and repeated names (one clear line naming ``where``)."""
    names = list(names)
    if not all(isinstance(n, str) and n.strip() for n in names):
        raise JaxmpmError(f"{where}: empty parameter name")
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise JaxmpmError(f"{where}: {', '.join(repeated)} given more than once")
    return names


def check_varied(model: Model, paths: dict[str, tuple], verb: str) -> None:
    """Raise before any rollout when a parameter to be ``verb`` (fitted, swept) is a collider's
    friction or restitution that has no effect in ``model``
    (:func:`jaxmpm.model.inert_contact_parameter`): its derivative would be exactly zero.

    Arguments:
        paths: ``{name: path}`` as :func:`resolve_name` gives them.
    """
    for name, path in paths.items():
        if path[0] == "colliders":
            why = inert_contact_parameter(model, path[1], path[2])
            if why is not None:
                raise JaxmpmError(f"parameter {name!r} cannot be {verb}: it has no effect on collider "
                                  f"{model.colliders[path[1]].name!r}: {why}")


def get_param(params: Params, path: tuple):
    node = params
    for key in path:
        node = node[key]
    return node


def set_param(params: Params, path: tuple, value) -> Params:
    """A copy of ``params`` with the leaf at ``path`` replaced (pure; works under tracing)."""
    if not path:
        return value
    key, rest = path[0], path[1:]
    if isinstance(params, dict):
        out = dict(params)
        out[key] = set_param(params[key], rest, value)
        return out
    out = list(params)
    out[key] = set_param(params[key], rest, value)
    return type(params)(out)


def with_values(model: Model, params: Params, values: dict) -> Params:
    """``params`` with each named parameter (:func:`resolve_name`) set to ``values[name]``,
    cast to the leaf's dtype."""
    for name, value in values.items():
        path = resolve_name(model, params, name)
        params = set_param(params, path, jnp.asarray(value, jnp.asarray(get_param(params, path)).dtype))
    return params


def apply_unconstrained(model: Model, params: Params, names, y: dict) -> Params:
    """``params`` with the named leaves set from optimisation variables (cast to the leaves' dtype)."""
    for name in names:
        path = resolve_name(model, params, name)
        dtype = jnp.asarray(get_param(params, path)).dtype
        params = set_param(params, path, from_unconstrained(name, y[name]).astype(dtype))
    return params


def default_names(model: Model) -> list[str]:
    """The material parameters that PAC-NeRF fits for a one-body scene's material."""
    if len(model.bodies) != 1:
        raise JaxmpmError("this scene has several bodies: name the parameters to fit")
    return list(MATERIALS[material_name(model.bodies[0])].required())

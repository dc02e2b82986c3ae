"""Refine the first frame's body with the differentiable surfel renderer.

The visual hull is the largest shape the silhouettes allow: few views leave excess corners.
:func:`refine_body` gives every hull particle an opacity and, when the views have colour, a
colour, fits both with Adam so that the surfel renderer (:class:`jaxmpm.render.SurfelRenderer`,
the renderer the body's silhouettes are compared with everywhere in :mod:`jaxmpm.reconstruct`)
reproduces the first frame's masks and, inside them, its RGB; particles whose opacity ends
below a threshold are removed. What goes are mostly the hull's excess corners, whose splats
spill over the silhouettes' borders (measured, docs/identify.md §3: a sphere seen from 4 views
loses half of its 13 % excess volume, 15 of the 17 particles removed lying outside it). The
colours were meant to carve a textured body's excess by photo-consistency (a particle off the
surface sees different colours from different views); at the measured resolution (96 px, a
body 20 px across) they changed nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..errors import ObservationError

__all__ = ["BodyRefinement", "adam_fit", "color_logits", "mean_over_views", "mean_view_error", "refine_body", "view_targets"]


@dataclass
class BodyRefinement:
    """The result of :func:`refine_body`.

    Attributes:
        points: ``(M, 3)`` the kept particles, m.
        opacity: ``(N,)`` every input particle's fitted opacity in [0, 1].
        colors: ``(M, 3)`` the kept particles' fitted RGB in [0, 1], or None (masks only).
        iou_before, iou_after: ``(V,)`` first-frame IoU of the re-projected silhouettes
            (default opacity, thresholded at 0.5) of the input and the kept particles.
        loss: ``(steps,)`` the fitted loss per Adam step.
    """

    points: np.ndarray
    opacity: np.ndarray
    colors: np.ndarray | None
    iou_before: np.ndarray
    iou_after: np.ndarray
    loss: np.ndarray

    @property
    def removed(self) -> int:
        """How many particles were removed."""
        return len(self.opacity) - len(self.points)


def adam_fit(loss: Callable, theta, data, steps: int, learning_rate: float,
             progress: Callable[[int, float], None] | None = None) -> tuple[object, list[float]]:
    """``steps`` Adam steps on the pytree ``theta`` minimising the scalar ``loss(theta, data)``
    (one jitted step); returns the final ``theta`` and the loss before each step, and calls
    ``progress(step, loss)`` after each.

    ``data`` is the pytree of arrays the loss compares with (masks, images, stacked cameras):
    an argument of the compiled step, not constants built into it, so the program's size and
    its compilation do not grow with the images."""
    import jax
    import optax

    opt = optax.adam(learning_rate)
    state = opt.init(theta)

    @jax.jit
    def update(theta, state, data):
        value, g = jax.value_and_grad(loss)(theta, data)
        with jax.numpy_dtype_promotion("standard"):  # optax mixes its int32 step count with floats
            upd, state = opt.update(g, state)
        return optax.apply_updates(theta, upd), state, value

    history = []
    for i in range(steps):
        theta, state, value = update(theta, state, data)
        history.append(float(value))
        if progress is not None:
            progress(i, history[-1])
    return theta, history


def mean_over_views(per_view: Callable, cameras, *views):
    """The mean over the views of ``per_view(camera, *view_data)``: ``cameras`` stacked
    (:func:`jaxmpm.render.stack_cameras`) and each of ``views`` an array (or pytree, or None)
    with the views along its leading axis. One view at a time (``jax.lax.map``): the
    renderer is traced and compiled once, whatever the number of views (a Python loop over
    them compiled one copy per view, and its gradient another)."""
    import jax
    import jax.numpy as jnp

    return jnp.mean(jax.lax.map(lambda args: per_view(*args), (cameras, *views)))


def view_targets(cams, masks: np.ndarray, images: np.ndarray | None) -> dict:
    """What a surfel fit compares with, as jit arguments: the stacked ``cams``, the masks
    ``(V, H, W)`` as 0/1 floats and the images ``(V, H, W, 3)`` (uint8) in [0, 1], or None."""
    import jax.numpy as jnp

    from ..render import stack_cameras

    return {
        "cameras": stack_cameras(cams),
        "target": jnp.asarray(masks, jnp.float32),
        "rgb": None if images is None else jnp.asarray(np.asarray(images, np.float32) / 255.0),
    }


def mean_view_error(render: Callable, views: dict, rgb_weight: float):
    """The mean over the views of the squared mask error, plus ``rgb_weight`` times the
    squared colour error inside the mask where ``views`` (:func:`view_targets`) has images.
    ``render(camera, colour)`` gives the alpha ``(H, W)`` when ``colour`` is False, else the
    renderer's output with ``alpha`` and ``rgb``."""
    import jax.numpy as jnp

    def view_error(cam, target, rgb):
        if rgb is None:
            return jnp.mean((render(cam, False) - target) ** 2)
        out = render(cam, True)
        return jnp.mean((out.alpha - target) ** 2) + rgb_weight * jnp.mean(target[..., None] * (out.rgb - rgb) ** 2)

    return mean_over_views(view_error, views["cameras"], views["target"], views["rgb"])


def color_logits(points: np.ndarray, images: np.ndarray, masks: np.ndarray, intrinsics, cam_to_world):
    """The logits of the particles' mean observed colours (:func:`jaxmpm.render.mean_colors`,
    clipped to [0.02, 0.98]): the starting point of a colour fit, ``(N, 3)`` float32."""
    import jax.numpy as jnp

    from ..render import mean_colors

    c0 = np.clip(mean_colors(points, np.asarray(images, float) / 255.0, masks, intrinsics, cam_to_world), 0.02, 0.98)
    return jnp.asarray(np.log(c0 / (1.0 - c0)), jnp.float32)


def refine_body(
    points: np.ndarray,
    masks: np.ndarray,
    intrinsics: np.ndarray,
    cam_to_world: np.ndarray,
    spacing: float,
    *,
    images: np.ndarray | None = None,
    steps: int = 60,
    learning_rate: float = 0.1,
    rgb_weight: float = 1.0,
    threshold: float = 0.5,
    progress: Callable[[int, float], None] | None = None,
) -> BodyRefinement:
    """Fit per-particle opacities (and colours) to the first frame's views; drop the transparent.

    The loss is the mean over views and pixels of ``(alpha − mask)²`` plus, with ``images``,
    ``rgb_weight ×`` the mean of ``mask · |rgb − image|²`` over pixels and channels.
    Opacities start at 0.95 (logit 3), colours at each particle's mean colour over the views
    where it projects inside the mask. A particle is kept when its opacity ends at or above
    ``threshold``.

    Arguments:
        points: ``(N, 3)`` particles of the hull, m.
        masks: ``(V, H, W)`` the first frame's masks (bool or 0/255).
        intrinsics, cam_to_world: ``(V, 3, 3)``, ``(V, 4, 4)`` (OpenCV axes).
        spacing: the particles' lattice spacing, m (sets the surfel size as everywhere).
        images: ``(V, H, W, 3)`` uint8 first-frame RGB, or None for masks only.
        steps, learning_rate: Adam iterations and step size (on logits).
        rgb_weight: weight of the colour term.
        threshold: opacity below which a particle is removed.
        progress: ``progress(step, loss)`` after each step.

    Returns:
        A :class:`BodyRefinement`.

    Raises:
        ObservationError: inputs of mismatched shapes, or every particle removed.
    """
    import jax
    import jax.numpy as jnp

    from ..render import Camera, SurfelRenderer
    from .hull import silhouette_iou

    points = np.asarray(points, float)
    masks = np.asarray(masks) > 0
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ObservationError(f"refine_body: points must have shape (N, 3) with N > 0, got {points.shape}")
    if masks.ndim != 3:
        raise ObservationError(f"refine_body: masks must have shape (V, H, W), got {masks.shape}")
    V, H, W = masks.shape
    if images is not None and np.shape(images) != (V, H, W, 3):
        raise ObservationError(f"refine_body: images have shape {np.shape(images)}; the masks need {(V, H, W, 3)}")
    K, P = np.asarray(intrinsics, float), np.asarray(cam_to_world, float)
    cams = [Camera(np.asarray(K[v], np.float32), np.asarray(P[v], np.float32), W, H) for v in range(V)]
    renderer = SurfelRenderer.for_particles(points, spacing=spacing)
    data = {"x": jnp.asarray(points, jnp.float32), **view_targets(cams, masks, images)}

    def loss(theta, data):
        o = jax.nn.sigmoid(theta["logit"])

        def render(cam, colour):
            if not colour:
                return renderer.silhouette(data["x"], cam, opacities=o)
            return renderer.render(data["x"], cam, jax.nn.sigmoid(theta["color"]), opacities=o)

        return mean_view_error(render, data, rgb_weight)

    theta = {"logit": jnp.full((len(points),), 3.0, jnp.float32)}
    if images is not None:
        theta["color"] = color_logits(points, images, masks, K, P)
    theta, history = adam_fit(loss, theta, data, steps, learning_rate, progress)
    opacity = np.asarray(jax.nn.sigmoid(theta["logit"]), float)
    keep = opacity >= threshold
    if not keep.any():
        raise ObservationError("refine_body: every particle became transparent: the masks hold no body")

    def iou(pts):
        sil = [renderer.silhouette(jnp.asarray(pts, jnp.float32), c) for c in cams]
        return silhouette_iou(np.asarray(jnp.stack(sil)) > 0.5, masks)

    colors = None if images is None else np.asarray(jax.nn.sigmoid(theta["color"]), float)[keep]
    return BodyRefinement(points=points[keep], opacity=opacity, colors=colors, iou_before=iou(points),
                          iou_after=iou(points[keep]), loss=np.asarray(history))

"""2D Gaussian surfel rendering of particles (2DGS, Huang et al., SIGGRAPH 2024), tile-free.

Each particle carries one surfel: centre ``p`` (the particle position), two tangent axes
``a_u = s_u t_u``, ``a_v = s_v t_v`` (scaled), opacity ``o`` and an RGB colour. Its points
are ``p + u a_u + v a_v`` and its footprint is the Gaussian ``G(u, v) = exp(−(u²+v²)/2)``.

**Exact ray–splat intersection.** In camera coordinates let ``m_u = R_wcᵀ a_u``,
``m_v = R_wcᵀ a_v``, ``m_p = R_wcᵀ(p − o)`` be the columns of the 3×3 matrix ``M`` mapping
``(u, v, 1)`` to camera space. The ray through the pixel with normalised coordinates
``r = K⁻¹(x, y, 1) = (x̃, ỹ, 1)`` is the intersection of the two planes
``x̃·Z − X = 0`` and ``ỹ·Z − Y = 0``; pulled back through ``M`` they become the
homogeneous vectors ``k = x̃·M₃ − M₁`` and ``l = ỹ·M₃ − M₂`` (``Mᵢ`` = rows of M) and
the intersection is ``(u, v, 1) ∝ k × l``:

    den = k₀l₁ − k₁l₀,   u = (k₁l₂ − k₂l₁)/den,   v = (k₂l₀ − k₀l₂)/den.

This is the homogeneous formulation of 2DGS (there written with ``K`` folded into M, in
pixel units; the two are projectively identical). ``den = r·(m_u × m_v)`` vanishes for an
edge-on surfel; hits with ``|cos| < 1e-4`` between ray and normal are dropped. The
intersection's depth is ``z = u m_u.z + v m_v.z + m_p.z``.
The opacity is ``α = min(α_max, o·exp(−ρ/2))`` with ``ρ = u² + v²``, zeroed below
``α_min`` (1/255), after a low-pass filter against aliasing of sub-pixel surfels
(``lowpass``):

* ``"mip"`` (default): an energy-preserving filter in the manner of Mip-Splatting's 2D
  filter. With ``s² = fx·fy·|det M|/m_p.z³`` the squared pixel size of one surfel unit
  at the centre (the local area scale of the (u, v) → pixel homography), the footprint is
  widened to variance ``s² + σ_f²`` and its opacity scaled by ``s²/(s² + σ_f²)``:
  ``ρ ← ρ·s²/(s² + σ_f²)``, ``o ← o·s²/(s² + σ_f²)`` (σ_f² = ``filter_variance`` px²).
  A body's outline then stays put when the surfels are smaller than a pixel.
* ``"2dgs"``: the original 2DGS rule ``ρ = min(u² + v², |c − (x, y)|²/σ²)``, ``c`` the
  projected centre, ``σ = √2/2`` px. With many overlapping surfels it grows a body's
  silhouette by one to two pixels when particles are smaller than pixels.
* ``None``: no filter.

**Compositing (tile-free, "dense sorted").** The surfels are sorted once per view by the
depth of their centres; for a chunk of pixels every pixel–surfel pair is evaluated and
``C = Σ_i c_i α_i Π_{j<i}(1 − α_j) + T·background`` is computed with a cumulative sum of
``log(1 − α)`` along the sorted axis. The result is exact up to the per-primitive sort
(the same approximation as 2DGS); it costs O(pixels × surfels) and memory
O(chunk × surfels). No early termination (it changes colours by < 1e-4).

**Silhouette.** ``1 − Π_i (1 − α_i)`` is independent of the order:
:meth:`SurfelRenderer.silhouette` computes it without sorting and without colours.

**Default surfel frame.** Disks facing the camera (normal towards the camera centre),
radius parameter ``s_u = s_v = scale`` (a fraction of the particle spacing), or given
normals, and optionally deformed by the particle's deformation gradient ``F``
(``a_u ← F a_u``, ``a_v ← F a_v``, as PhysGaussian).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..errors import ObservationError
from .camera import Camera
from .volume import (
    AbstractRenderer,
    Rendered,
    _finish,
    _prepare,
    estimate_spacing,
    map_pixel_chunks,
    safe_divide,
)

_COS_MIN = 1e-4
_RHO_MAX = 200.0


def _normalize(v):
    return v / jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True) + 1e-30)


class SurfelRenderer(AbstractRenderer):
    """One 2D Gaussian surfel per particle, exact ray–splat intersection, sorted compositing.

    Build it with :meth:`for_particles` to get the scale from the particle spacing.

    Attributes:
        scale: Gaussian standard deviation of the surfel disks, m (``s_u = s_v``).
        opacity: surfel opacity ``o`` (per-particle values can be passed to :meth:`render`).
        alpha_min: contributions below this are dropped (2DGS: 1/255).
        alpha_max: per-surfel opacity cap (2DGS: 0.99).
        lowpass: anti-aliasing filter, ``"mip"`` (default), ``"2dgs"`` or ``None``.
        filter_variance: variance (px²) of the ``"mip"`` filter.
        background: RGB background colour.
        chunk_size: pixels per chunk; ``None`` chooses about 2²¹ pixel–surfel pairs.
        near: surfels (and hits) closer than this to the camera plane are ignored.
    """

    scale: float = eqx.field(static=True)
    opacity: float = eqx.field(static=True, default=1.0)
    alpha_min: float = eqx.field(static=True, default=1.0 / 255.0)
    alpha_max: float = eqx.field(static=True, default=0.99)
    lowpass: str | None = eqx.field(static=True, default="mip")
    filter_variance: float = eqx.field(static=True, default=0.1)
    background: tuple[float, float, float] = eqx.field(static=True, default=(1.0, 1.0, 1.0))
    chunk_size: int | None = eqx.field(static=True, default=None)
    near: float = eqx.field(static=True, default=1e-3)

    def __check_init__(self):
        if not self.scale > 0:
            raise ObservationError(f"surfel scale must be positive, got {self.scale}")
        if self.lowpass not in ("mip", "2dgs", None):
            raise ObservationError(f"lowpass must be 'mip', '2dgs' or None, got {self.lowpass!r}")
        if not 0.0 < self.alpha_max <= 1.0:
            raise ObservationError(f"alpha_max must be in (0, 1], got {self.alpha_max}")

    #: Default surfel scale as a fraction of the particle spacing (calibrated so that a
    #: densely sampled sphere's silhouette matches the sphere's outline; see
    #: docs/rendering.md).
    SCALE_FACTOR = 0.28

    @classmethod
    def for_particles(
        cls, positions, *, spacing: float | None = None, scale_factor: float | None = None, **options
    ) -> SurfelRenderer:
        """A renderer with ``scale = scale_factor · spacing`` (spacing estimated from
        ``positions`` unless given; ``scale_factor`` defaults to :attr:`SCALE_FACTOR`)."""
        h = estimate_spacing(positions) if spacing is None else float(spacing)
        if not h > 0:
            raise ObservationError(f"particle spacing must be positive, got {h}")
        f = cls.SCALE_FACTOR if scale_factor is None else float(scale_factor)
        return cls(scale=f * h, **options)

    def _chunk(self, n: int) -> int:
        if self.chunk_size is not None:
            return int(self.chunk_size)
        return int(min(4096, max(16, (1 << 21) // max(n, 1))))

    # --- surfel geometry --------------------------------------------------------------

    def surfel_axes(
        self,
        positions: Float[Array, "N 3"],
        camera: Camera,
        *,
        normals: Float[Array, "N 3"] | None = None,
        F: Float[Array, "N 3 3"] | None = None,
        scales: Float[Array, "N 2"] | Float[Array, " N"] | None = None,
    ) -> tuple[Float[Array, "N 3"], Float[Array, "N 3"]]:
        """World-space scaled tangent axes ``(a_u, a_v)`` of every surfel.

        Without ``normals`` the disks face the camera centre; ``scales`` (``(N,)`` or
        ``(N, 2)``) override :attr:`scale`; ``F`` deforms the scaled axes.
        """
        dtype = positions.dtype
        if normals is None:
            n = _normalize(camera.position - positions)
            ref = jnp.broadcast_to(camera.rotation[:, 1], positions.shape)  # camera "down"
        else:
            if normals.shape != positions.shape:
                raise ObservationError(f"normals must have shape {positions.shape}, got {normals.shape}")
            n = _normalize(normals.astype(dtype))
            ex = jnp.asarray([1.0, 0.0, 0.0], dtype=dtype)
            ey = jnp.asarray([0.0, 1.0, 0.0], dtype=dtype)
            ref = jnp.where(jnp.abs(n[:, :1]) < 0.9, ex, ey)
        tu = _normalize(jnp.cross(ref, n))
        tv = jnp.cross(n, tu)
        if scales is None:
            su = sv = jnp.asarray(self.scale, dtype=dtype)
        else:
            scales = jnp.asarray(scales).astype(dtype)
            if scales.ndim == 1:
                su = sv = scales[:, None]
            else:
                su, sv = scales[:, :1], scales[:, 1:2]
        au, av = su * tu, sv * tv
        if F is not None:
            if F.shape != positions.shape + (3,):
                raise ObservationError(f"F must have shape {positions.shape + (3,)}, got {F.shape}")
            F = F.astype(dtype)
            au = jnp.einsum("nij,nj->ni", F, au)
            av = jnp.einsum("nij,nj->ni", F, av)
        return au, av

    def _surfel_terms(self, positions, camera, au, av):
        """Camera-space columns m_u, m_v, m_p (N, 3) and projected centres (N, 2)."""
        R = camera.rotation
        mu = au @ R
        mv = av @ R
        mp = (positions - camera.position) @ R
        centre, _ = camera.project(positions)
        # local area scale of the (u, v) -> pixel map at the centre: fx·fy·det(M)/z³ px²
        # per unit (u, v) area, i.e. the squared pixel size of one unit of the surfel
        z = mp[:, 2]
        z_safe = jnp.where(z > self.near, z, self.near)
        detM = jnp.sum(jnp.cross(mu, mv) * mp, axis=-1)
        s2 = camera.K[0, 0] * camera.K[1, 1] * jnp.abs(detM) / z_safe**3
        footprint = s2 / (s2 + self.filter_variance)  # mip low-pass: energy-preserving
        return mu, mv, mp, centre, footprint

    def _alpha_and_depth(self, terms, opac, camera: Camera, pix):
        """Per pixel–surfel opacity ``(C, N)`` and hit depth ``(C, N)`` for pixels ``pix``."""
        mu, mv, mp, centre, footprint = terms
        dtype = mu.dtype
        xy = camera.pixel_coordinates(pix)  # (C, 2)
        r = camera._camera_dirs(xy)  # (C, 3), z = 1
        xt, yt = r[:, 0:1], r[:, 1:2]
        # rows of M: M1 = (mu.x, mv.x, mp.x), M2 = (.y), M3 = (.z)
        k0 = xt * mu[:, 2] - mu[:, 0]
        k1 = xt * mv[:, 2] - mv[:, 0]
        k2 = xt * mp[:, 2] - mp[:, 0]
        l0 = yt * mu[:, 2] - mu[:, 1]
        l1 = yt * mv[:, 2] - mv[:, 1]
        l2 = yt * mp[:, 2] - mp[:, 1]
        den = k0 * l1 - k1 * l0
        cr = jnp.cross(mu, mv)  # (N, 3)
        cr_norm = jnp.sqrt(jnp.sum(cr * cr, axis=-1) + 1e-30)
        r_norm = jnp.sqrt(jnp.sum(r * r, axis=-1, keepdims=True))
        ok = jnp.abs(den) > _COS_MIN * r_norm * cr_norm
        den_safe = jnp.where(ok, den, 1.0)
        u = jnp.where(ok, (k1 * l2 - k2 * l1) / den_safe, 0.0)
        v = jnp.where(ok, (k2 * l0 - k0 * l2) / den_safe, 0.0)
        rho3 = jnp.where(ok, jnp.minimum(u * u + v * v, _RHO_MAX), _RHO_MAX)
        z_hit = u * mu[:, 2] + v * mv[:, 2] + mp[:, 2]
        z_ctr = jnp.broadcast_to(mp[:, 2], z_hit.shape)
        if self.lowpass == "2dgs":
            dxy = xy[:, None, :] - centre[None, :, :]
            rho2 = jnp.minimum(2.0 * jnp.sum(dxy * dxy, axis=-1), _RHO_MAX)  # σ² = 1/2 px²
            use3 = rho3 <= rho2
            rho = jnp.where(use3, rho3, rho2)
            z = jnp.where(use3, z_hit, z_ctr)
        elif self.lowpass == "mip":
            rho, z = rho3 * footprint, z_hit
            opac = opac * footprint
        else:
            rho, z = rho3, z_hit
        alpha = jnp.minimum(self.alpha_max, opac * jnp.exp(-0.5 * rho))
        valid = (alpha >= self.alpha_min) & (z > self.near) & (mp[:, 2] > self.near)
        alpha = jnp.where(valid, alpha, jnp.zeros((), dtype))
        return alpha, z

    def _opacities(self, positions, opacities):
        dtype = positions.dtype
        if opacities is None:
            return jnp.full(positions.shape[:1], self.opacity, dtype=dtype)
        return jnp.broadcast_to(jnp.asarray(opacities).astype(dtype), positions.shape[:1])

    # --- rendering -------------------------------------------------------------------

    def render(
        self,
        positions: Float[Array, "N 3"],
        camera: Camera,
        colors: Float[Array, "N 3"] | None = None,
        *,
        pixels: Int[Array, " P"] | None = None,
        normals: Float[Array, "N 3"] | None = None,
        F: Float[Array, "N 3 3"] | None = None,
        scales: Float[Array, "N 2"] | Float[Array, " N"] | None = None,
        opacities: Float[Array, " N"] | None = None,
    ) -> Rendered:
        """Render one view with depth-sorted compositing.

        Arguments:
            positions: ``(N, 3)`` surfel centres (output dtype = their dtype).
            camera: a single camera.
            colors: ``(N, 3)`` RGB in [0, 1] (default: one colour).
            pixels: flat pixel indices to render (default: the full image).
            normals: surfel normals ``(N, 3)`` (default: facing the camera).
            F: deformation gradients ``(N, 3, 3)`` applied to the surfel axes.
            scales: per-surfel scales ``(N,)`` or ``(N, 2)`` (default :attr:`scale`).
            opacities: per-surfel opacities ``(N,)`` (default :attr:`opacity`).

        Returns:
            :class:`Rendered` with ``(H, W, ...)`` or ``(P, ...)`` arrays.
        """
        camera, colors = _prepare(positions, camera, colors)
        dtype = positions.dtype
        au, av = self.surfel_axes(positions, camera, normals=normals, F=F, scales=scales)
        opac = self._opacities(positions, opacities)
        terms = self._surfel_terms(positions, camera, au, av)
        order = jnp.argsort(jax.lax.stop_gradient(terms[2][:, 2]))
        terms = tuple(t[order] for t in terms)
        opac, colors = opac[order], colors[order]
        bg = jnp.asarray(self.background, dtype=dtype)

        def chunk_fn(pix):
            alpha, z = self._alpha_and_depth(terms, opac, camera, pix)
            log_keep = jnp.log1p(-alpha)
            csum = jnp.cumsum(log_keep, axis=-1)
            w = alpha * jnp.exp(csum - log_keep)
            t_final = jnp.exp(csum[:, -1])
            acc = 1.0 - t_final
            rgb = w @ colors + t_final[:, None] * bg
            depth = safe_divide(jnp.sum(w * z, axis=-1), acc)
            return Rendered(rgb, acc, depth)

        out = map_pixel_chunks(chunk_fn, camera, pixels, self._chunk(positions.shape[0]))
        return _finish(out, camera, pixels)

    def silhouette(
        self,
        positions: Float[Array, "N 3"],
        camera: Camera,
        *,
        pixels: Int[Array, " P"] | None = None,
        normals: Float[Array, "N 3"] | None = None,
        F: Float[Array, "N 3 3"] | None = None,
        scales: Float[Array, "N 2"] | Float[Array, " N"] | None = None,
        opacities: Float[Array, " N"] | None = None,
    ) -> Float[Array, "..."]:
        """Order-independent soft silhouette ``1 − Π(1 − α_i)``: no sort, no colour.

        Returns ``(H, W)``, or ``(P,)`` for a pixel list. Equal to ``render(...).alpha``.
        """
        _check = _prepare(positions, camera, None)
        camera = _check[0]
        au, av = self.surfel_axes(positions, camera, normals=normals, F=F, scales=scales)
        opac = self._opacities(positions, opacities)
        terms = self._surfel_terms(positions, camera, au, av)

        def chunk_fn(pix):
            alpha, _ = self._alpha_and_depth(terms, opac, camera, pix)
            return -jnp.expm1(jnp.sum(jnp.log1p(-alpha), axis=-1))

        out = map_pixel_chunks(chunk_fn, camera, pixels, self._chunk(positions.shape[0]))
        if pixels is None:
            return out.reshape(camera.height, camera.width)
        return out

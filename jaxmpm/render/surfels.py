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

**Compositing (tile-free, sorted).** The surfels are sorted once per view by the depth of
their centres; for a chunk of pixels the pixel–surfel opacities are evaluated and
``C = Σ_i c_i α_i Π_{j<i}(1 − α_j) + T·background`` is computed with a cumulative sum of
``log(1 − α)`` along the sorted axis. The result is exact up to the per-primitive sort
(the same approximation as 2DGS). No early termination (it changes colours by < 1e-4).

**Culling per chunk.** Every surfel gets a conservative pixel box outside which its α is
below ``α_min`` (the projection of the square ``|u|, |v| ≤ c`` with
``o·exp(−c²/2) = α_min``, widened by the filter). Chunks are narrow bands of rows (pixel
lists are processed in raster order); a chunk composites only the first K surfels, in
depth order, whose box meets it (``lax.top_k`` on the sorted ranks), and falls back to all
N surfels through ``lax.cond`` when more than K qualify. Since the dropped surfels
contribute α = 0 exactly, the image is the same as without culling, at a cost of
O(pixels × K) instead of O(pixels × N). K defaults to N/4 from 8192 surfels on.

**Silhouette.** ``1 − Π_i (1 − α_i)`` is independent of the order:
:meth:`SurfelRenderer.silhouette` computes it without sorting and without colours.

**Default surfel frame.** Disks facing the camera (normal towards the camera centre),
radius parameter ``s_u = s_v = scale`` (a fraction of the particle spacing), or given
normals, and optionally deformed by the particle's deformation gradient ``F``
(``a_u ← F a_u``, ``a_v ← F a_v``, as PhysGaussian).
"""

from __future__ import annotations


import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..errors import ObservationError
from ..precision import compiled_entry
from .camera import Camera
from .volume import (
    AbstractRenderer,
    Rendered,
    composite,
    estimate_spacing,
    finish_image,
    map_pixel_chunks,
    prepare_inputs,
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
        chunk_size: pixels per chunk; ``None`` chooses about 2²¹ pixel–surfel pairs
            (and, when culling, about one image row's worth of the requested pixels).
        max_candidates: K, the number of surfels a chunk of pixels composites when
            culling (see the module docstring); ``None``: ``N // 4`` for N ≥ 8192
            surfels, no culling below; ``0``: never cull.
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
    max_candidates: int | None = eqx.field(static=True, default=None)
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

    def _num_candidates(self, n: int) -> int:
        """K (static); K >= n means no culling."""
        if self.alpha_min <= 0.0 or self.max_candidates == 0:
            return n
        if self.max_candidates is None:
            return n // 4 if n >= 8192 else n
        return min(int(self.max_candidates), n)

    def _chunk(self, n: int, num_pixels: int, height: int) -> int:
        """Pixels per chunk: about 2²¹ pixel–surfel pairs; when culling, also about one
        image row's worth of the requested pixels (a narrow band of rows)."""
        if self.chunk_size is not None:
            return int(self.chunk_size)
        k = self._num_candidates(n)
        c = (1 << 21) // max(k, 1)
        if k < n:
            c = min(c, max(num_pixels // height, 1))
        return int(min(4096, max(16, c)))

    def _screen_boxes(self, positions, camera: Camera, au, av, opac, footprint):
        """Conservative pixel-space boxes ``(N, 4)`` = (x0, x1, y0, y1) outside which a
        surfel's α is below ``alpha_min`` (no gradient flows through them)."""
        sg = jax.lax.stop_gradient
        positions, au, av, opac, footprint = map(sg, (positions, au, av, opac, footprint))
        dtype = positions.dtype
        amin = self.alpha_min
        if self.lowpass == "mip":
            o = opac * footprint
            c = jnp.sqrt(jnp.maximum(2.0 * jnp.log(jnp.maximum(o, 1e-30) / amin), 0.0) / footprint)
        else:
            o = opac
            c = jnp.sqrt(jnp.maximum(2.0 * jnp.log(jnp.maximum(o, 1e-30) / amin), 0.0))
        corners = []
        for su, sv in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
            corners.append(positions + c[:, None] * (su * au + sv * av))
        uv, z = camera.project(jnp.stack(corners, axis=1))  # (N, 4, 2), (N, 4)
        lo = jnp.min(uv, axis=1) - 0.5
        hi = jnp.max(uv, axis=1) + 0.5
        if self.lowpass == "2dgs":  # the pixel-space filter: a disc around the centre
            ctr, _ = camera.project(positions)
            r2 = jnp.sqrt(jnp.maximum(jnp.log(jnp.maximum(o, 1e-30) / amin), 0.0))[:, None] + 0.5
            lo = jnp.minimum(lo, ctr - r2)
            hi = jnp.maximum(hi, ctr + r2)
        big = jnp.asarray(1e9, dtype)
        behind = jnp.any(z <= self.near, axis=1)[:, None]
        lo = jnp.where(behind, -big, lo)
        hi = jnp.where(behind, big, hi)
        invisible = (o < amin)[:, None]
        lo = jnp.where(invisible, big, lo)
        hi = jnp.where(invisible, -big, hi)
        return jnp.stack([lo[:, 0], hi[:, 0], lo[:, 1], hi[:, 1]], axis=-1)

    def _pixel_loop(self, pair_fn, surfels, boxes, camera: Camera, pixels):
        """Run ``pair_fn(surfels, pix) -> outputs (C, ...)`` over pixel chunks.

        ``surfels`` is a tuple of pytrees of ``(N, ...)`` arrays in compositing order whose
        second element is the opacity ``(N,)``. With culling, each chunk keeps the first K surfels (in
        that order) whose box meets the chunk's pixels, zeroing the opacity of unused
        slots, and falls back to all N surfels when more than K qualify — so the result
        is always exact.
        """
        n = surfels[1].shape[0]
        k = self._num_candidates(n)
        num_pixels = camera.num_pixels if pixels is None else int(np.shape(pixels)[0])
        chunk = self._chunk(n, num_pixels, camera.height)
        if k >= n:
            return map_pixel_chunks(lambda pix: pair_fn(surfels, pix), camera, pixels, chunk)
        unsort = None
        if pixels is not None:  # raster order keeps each chunk in a narrow band of rows
            pixels = jnp.asarray(pixels).astype(jnp.int32)
            order = jnp.argsort(pixels)
            unsort = jnp.argsort(order)
            pixels = pixels[order]
        dtype = boxes.dtype
        rank = n - jnp.arange(n, dtype=jnp.int32)

        def chunk_fn(pix):
            row = pix // camera.width
            col = pix - row * camera.width
            x0 = jnp.min(col).astype(dtype) + 0.5
            x1 = jnp.max(col).astype(dtype) + 0.5
            y0 = jnp.min(row).astype(dtype) + 0.5
            y1 = jnp.max(row).astype(dtype) + 0.5
            hit = (boxes[:, 1] >= x0) & (boxes[:, 0] <= x1) & (boxes[:, 3] >= y0) & (boxes[:, 2] <= y1)
            _, idx = jax.lax.top_k(jnp.where(hit, rank, 0), k)

            def culled(pix):
                sub = jax.tree_util.tree_map(lambda a: a[idx], surfels)
                opac = sub[1] * hit[idx].astype(sub[1].dtype)
                return pair_fn(sub[:1] + (opac,) + sub[2:], pix)

            def dense(pix):
                return pair_fn(surfels, pix)

            return jax.lax.cond(jnp.sum(hit.astype(jnp.int32)) <= k, culled, dense, pix)

        out = map_pixel_chunks(chunk_fn, camera, pixels, chunk)
        if unsort is not None:
            out = jax.tree_util.tree_map(lambda a: a[unsort], out)
        return out

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
        """Per-surfel quantities for the pixel loop, a tuple of ``(N, ...)`` arrays:
        ``adj (N, 3, 3)`` the adjugate of M, ``det (N,)``, the edge-on threshold
        ``(N,)``, projected centres ``(N, 2)``, the mip footprint factor ``(N,)`` and the
        centres' depth ``(N,)``."""
        R = camera.rotation
        mu = au @ R
        mv = av @ R
        mp = (positions - camera.position) @ R
        # adj(M) rows: so that adj(M)·M = det(M)·I for M = [m_u | m_v | m_p]
        n_uv = jnp.cross(mu, mv)
        adj = jnp.stack([jnp.cross(mv, mp), jnp.cross(mp, mu), n_uv], axis=1)
        det = jnp.sum(n_uv * mp, axis=-1)
        thr = _COS_MIN * jnp.sqrt(jnp.sum(n_uv * n_uv, axis=-1) + 1e-30)
        centre, _ = camera.project(positions)
        # local area scale of the (u, v) -> pixel map at the centre: fx·fy·det(M)/z³ px²
        # per unit (u, v) area, i.e. the squared pixel size of one unit of the surfel
        zc = mp[:, 2]
        z_safe = jnp.where(zc > self.near, zc, self.near)
        s2 = camera.K[0, 0] * camera.K[1, 1] * jnp.abs(det) / z_safe**3
        footprint = s2 / (s2 + self.filter_variance)  # mip low-pass: energy-preserving
        return adj, det, thr, centre, footprint, zc

    def _alpha_and_depth(self, terms, opac, camera: Camera, pix):
        """Per pixel–surfel opacity ``(C, N)`` and hit depth ``(C, N)`` for pixels ``pix``.

        With ``r = (x̃, ỹ, 1)`` the pixel's normalised ray, ``h = adj(M)·r`` is
        ``det(M)·M⁻¹r ∝ (u, v, 1)`` — the cross product ``k × l`` of 2DGS — so
        ``u = h₀/h₂``, ``v = h₁/h₂`` and the hit's depth is ``det(M)/h₂``.
        """
        adj, det, thr, centre, footprint, zc = terms
        dtype = adj.dtype
        xy = camera.pixel_coordinates(pix)  # (C, 2)
        r = camera.camera_dirs(xy)  # (C, 3), z = 1
        xt, yt = r[:, 0:1], r[:, 1:2]
        h0 = xt * adj[:, 0, 0] + yt * adj[:, 0, 1] + adj[:, 0, 2]
        h1 = xt * adj[:, 1, 0] + yt * adj[:, 1, 1] + adj[:, 1, 2]
        h2 = xt * adj[:, 2, 0] + yt * adj[:, 2, 1] + adj[:, 2, 2]  # = r·(m_u × m_v)
        r_norm = jnp.sqrt(jnp.sum(r * r, axis=-1, keepdims=True))
        ok = jnp.abs(h2) > thr * r_norm  # not edge-on
        inv = 1.0 / jnp.where(ok, h2, 1.0)
        u = h0 * inv
        v = h1 * inv
        rho3 = jnp.where(ok, jnp.minimum(u * u + v * v, _RHO_MAX), _RHO_MAX)
        z_hit = jnp.where(ok, det * inv, zc)
        if self.lowpass == "2dgs":
            dxy = xy[:, None, :] - centre[None, :, :]
            rho2 = jnp.minimum(2.0 * jnp.sum(dxy * dxy, axis=-1), _RHO_MAX)  # σ² = 1/2 px²
            use3 = rho3 <= rho2
            rho = jnp.where(use3, rho3, rho2)
            z = jnp.where(use3, z_hit, zc)
        elif self.lowpass == "mip":
            rho, z = rho3 * footprint, z_hit
            opac = opac * footprint
        else:
            rho, z = rho3, z_hit
        alpha = jnp.minimum(self.alpha_max, opac * jnp.exp(-0.5 * rho))
        valid = (alpha >= self.alpha_min) & (z > self.near) & (zc > self.near)
        alpha = jnp.where(valid, alpha, jnp.zeros((), dtype))
        return alpha, z

    def _opacities(self, positions, opacities):
        dtype = positions.dtype
        if opacities is None:
            return jnp.full(positions.shape[:1], self.opacity, dtype=dtype)
        return jnp.broadcast_to(jnp.asarray(opacities).astype(dtype), positions.shape[:1])

    # --- rendering -------------------------------------------------------------------

    @compiled_entry
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
        camera, colors = prepare_inputs(positions, camera, colors)
        dtype = positions.dtype
        au, av = self.surfel_axes(positions, camera, normals=normals, F=F, scales=scales)
        opac = self._opacities(positions, opacities)
        terms = self._surfel_terms(positions, camera, au, av)
        boxes = self._screen_boxes(positions, camera, au, av, opac, terms[4])
        order = jnp.argsort(jax.lax.stop_gradient(terms[-1]))  # centres' depth
        surfels = (terms, opac, colors, boxes)
        surfels = jax.tree_util.tree_map(lambda a: a[order], surfels)
        terms, opac, colors, boxes = surfels
        bg = jnp.asarray(self.background, dtype=dtype)

        def pair_fn(surf, pix):
            terms, opac, colors = surf
            alpha, z = self._alpha_and_depth(terms, opac, camera, pix)
            return composite(alpha, jnp.log1p(-alpha), z, lambda w: w @ colors, bg)

        out = self._pixel_loop(pair_fn, (terms, opac, colors), boxes, camera, pixels)
        return finish_image(out, camera, pixels)

    @compiled_entry
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
        _check = prepare_inputs(positions, camera, None)
        camera = _check[0]
        au, av = self.surfel_axes(positions, camera, normals=normals, F=F, scales=scales)
        opac = self._opacities(positions, opacities)
        terms = self._surfel_terms(positions, camera, au, av)
        boxes = self._screen_boxes(positions, camera, au, av, opac, terms[4])

        def pair_fn(surf, pix):
            terms, opac = surf
            alpha, _ = self._alpha_and_depth(terms, opac, camera, pix)
            return -jnp.expm1(jnp.sum(jnp.log1p(-alpha), axis=-1))

        out = self._pixel_loop(pair_fn, (terms, opac), boxes, camera, pixels)
        if pixels is None:
            return out.reshape(camera.height, camera.width)
        return out

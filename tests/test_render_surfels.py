"""2D Gaussian surfels: exact ray–splat intersection, compositing order, projected areas,
agreement with the volume renderer."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiles import counting_compilations

from jaxmpm.render import SurfelRenderer, VolumeRenderer, look_at

H = 0.03
R = 0.3


def sphere_particles(radius, h, centre=(0.0, 0.0, 0.0)):
    """Lattice points of spacing h inside a sphere, and the radius of the volume they fill."""
    n = int(np.ceil(radius / h)) + 1
    g = np.arange(-n, n + 1) * h
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    x = x[np.linalg.norm(x, axis=1) < radius]
    r_eff = (3.0 * x.shape[0] * h**3 / (4.0 * np.pi)) ** (1.0 / 3.0)
    return x + np.asarray(centre), r_eff


def projected_sphere(cam, centre, radius):
    """Exact perspective image of a sphere: (area in px², ellipse centre in px)."""
    K = np.asarray(cam.K, np.float64)
    c2w = np.asarray(cam.cam_to_world, np.float64)
    pc = c2w[:3, :3].T @ (np.asarray(centre, np.float64) - c2w[:3, 3])
    L2 = pc @ pc
    chat = pc / np.sqrt(L2)
    Q = np.outer(chat, chat) - (1.0 - radius**2 / L2) * np.eye(3)
    A, b, c = Q[:2, :2], Q[:2, 2], Q[2, 2]
    x0 = -np.linalg.solve(A, b)
    k = c - b @ np.linalg.solve(A, b)
    area = np.pi * abs(k) / np.sqrt(np.linalg.det(A)) * K[0, 0] * K[1, 1]
    return area, (K @ np.append(x0, 1.0))[:2]


def alpha_centroid(alpha):
    a = np.asarray(alpha, np.float64)
    rows, cols = np.mgrid[: a.shape[0], : a.shape[1]]
    return np.array([(a * (cols + 0.5)).sum(), (a * (rows + 0.5)).sum()]) / a.sum()


@pytest.mark.x64
@pytest.mark.parametrize("case", ["facing", "normal", "deformed"])
def test_single_surfel_matches_ray_plane_intersection(case):
    """α at every pixel equals o·exp(−(u²+v²)/2) of the exact ray–plane hit (float64)."""
    cam = look_at((0.2, 0.1, -1.0), (0, 0, 0), fov_deg=40.0, width=24, height=20, dtype=jnp.float64)
    p = np.array([[0.02, -0.03, 0.05]])
    rend = SurfelRenderer(scale=0.04, opacity=0.8, lowpass=None, alpha_min=0.0, alpha_max=1.0)
    kw = {}
    if case != "facing":
        kw["normals"] = jnp.asarray([[0.3, -0.4, -1.0]], jnp.float64)
    if case == "deformed":
        kw["F"] = jnp.asarray([[[1.8, 0.3, 0.0], [0.1, 0.7, 0.2], [0.0, 0.4, 1.1]]], jnp.float64)
    out = jax.jit(lambda x: rend.render(x, cam, **kw))(jnp.asarray(p, jnp.float64))
    au, av = (np.asarray(a)[0] for a in rend.surfel_axes(jnp.asarray(p, jnp.float64), cam, **kw))
    o, d = (np.asarray(a) for a in cam.rays())
    # solve p + u au + v av = o + t d for (u, v, t)
    A = np.stack([np.broadcast_to(au, d.shape), np.broadcast_to(av, d.shape), -d], axis=-1)
    u, v, t = np.moveaxis(np.linalg.solve(A, (o - p)[..., None])[..., 0], -1, 0)
    expect = 0.8 * np.exp(-0.5 * (u * u + v * v))
    np.testing.assert_allclose(np.asarray(out.alpha).reshape(-1), expect, atol=1e-9)
    assert expect.max() > 0.5 and expect.min() < 0.05
    z = t * (d @ np.asarray(cam.rotation)[:, 2])
    hit = expect > 1e-3
    np.testing.assert_allclose(np.asarray(out.depth).reshape(-1)[hit], z[hit], rtol=1e-9)


@pytest.mark.x64
def test_compositing_is_depth_sorted():
    # odd size: the centre pixel (4, 4) looks straight at both surfels' centres (α = 0.99)
    cam = look_at((0, 0, -2.0), (0, 0, 0), fov_deg=30.0, width=9, dtype=jnp.float64)
    rend = SurfelRenderer(scale=0.2, lowpass=None)
    colors = jnp.asarray([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], jnp.float64)
    near_red = jnp.asarray([[0.0, 0.0, -0.2], [0.0, 0.0, 0.2]], jnp.float64)
    render = jax.jit(lambda x: rend.render(x, cam, colors))
    a = render(near_red)
    b = render(near_red[::-1])  # blue in front
    bg = 0.01 * 0.01  # white background behind two surfels of opacity 0.99
    np.testing.assert_allclose(np.asarray(a.rgb[4, 4]), [0.99 + bg, bg, 0.0099 + bg], atol=1e-9)
    np.testing.assert_allclose(np.asarray(b.rgb[4, 4]), [0.0099 + bg, bg, 0.99 + bg], atol=1e-9)
    assert float(a.alpha[4, 4]) == pytest.approx(0.9999, abs=1e-12)
    assert float(a.depth[4, 4]) == pytest.approx((0.99 * 1.8 + 0.0099 * 2.2) / 0.9999, rel=1e-9)


def test_surfel_sphere_area_placement_and_order_independent_silhouette():
    x, r_eff = sphere_particles(R, H)
    cam = look_at((0.0, 0.0, -2.0), (0.0, 0.0, 0.0), fov_deg=40.0, width=64, dtype=jnp.float32)
    # K = 1024 of 4139 surfels per chunk: the culled path (exact, checked below)
    rend = SurfelRenderer.for_particles(x, spacing=H, max_candidates=1024)
    render = jax.jit(rend.render)
    sil = jax.jit(rend.silhouette)
    out = render(jnp.asarray(x, jnp.float32), cam)
    assert out.rgb.dtype == jnp.float32 and out.rgb.shape == (64, 64, 3)
    area, _ = projected_sphere(cam, (0, 0, 0), r_eff)
    assert float(out.alpha.sum()) == pytest.approx(area, rel=0.05)
    np.testing.assert_allclose(
        np.asarray(sil(jnp.asarray(x, jnp.float32), cam)), np.asarray(out.alpha), atol=1e-5
    )
    # semi-transparent sub-pixel surfels: the expected depth averages a few particle layers
    assert float(out.depth[32, 32]) == pytest.approx(2.0 - r_eff + H, abs=2 * H)
    off = np.array([0.35, -0.25, 0.2])
    alpha2 = sil(jnp.asarray(x + off, jnp.float32), cam)
    area2, centre2 = projected_sphere(cam, off, r_eff)
    assert float(alpha2.sum()) == pytest.approx(area2, rel=0.05)
    np.testing.assert_allclose(alpha_centroid(alpha2), centre2, atol=0.5)


def test_renderers_agree_on_silhouette():
    """An oblique view of a box with a sphere on top: both masks overlap with IoU > 0.9."""
    h = 0.03
    g = np.arange(-0.3, 0.3 + 1e-9, h)
    box = np.stack(np.meshgrid(g, g[:8], g[:12], indexing="ij"), -1).reshape(-1, 3)
    ball, _ = sphere_particles(0.18, h, centre=(0.1, 0.37, 0.0))
    x = np.concatenate([box, ball])
    cam = look_at((1.2, 1.0, -1.6), (0.0, 0.1, 0.0), fov_deg=40.0, width=48, dtype=jnp.float32)
    xj = jnp.asarray(x, jnp.float32)
    a = np.asarray(jax.jit(VolumeRenderer.for_particles(x, spacing=h).silhouette)(xj, cam)) > 0.5
    b = np.asarray(jax.jit(SurfelRenderer.for_particles(x, spacing=h).silhouette)(xj, cam)) > 0.5
    iou = (a & b).sum() / (a | b).sum()
    assert a.sum() > 200 and iou > 0.9, iou


def test_culling_is_exact_with_and_without_overflow():
    """Per-chunk candidate lists give the dense result, also when a chunk overflows K
    (fallback to all surfels) and for an unordered pixel list."""
    x, _ = sphere_particles(0.2, 0.04)
    x = x + np.random.default_rng(0).uniform(-0.01, 0.01, x.shape)
    cam = look_at((0.15, 0.25, -0.6), (0, 0, 0), fov_deg=40.0, width=24, height=20, dtype=jnp.float32)
    colors = jax.random.uniform(jax.random.key(0), (x.shape[0], 3), jnp.float32)
    xj = jnp.asarray(x, jnp.float32)
    pix = jax.random.permutation(jax.random.key(1), 480)[:150].astype(jnp.int32)
    outs = []
    # K = 100: chunks near the top and bottom of the sphere cull (they meet fewer boxes),
    # chunks across its middle overflow and take the dense path
    for k in (0, 100):
        rend = SurfelRenderer.for_particles(x, spacing=0.04, max_candidates=k, chunk_size=24)
        outs.append(jax.jit(lambda x, p: rend.render(x, cam, colors, pixels=p))(xj, pix))
    np.testing.assert_allclose(np.asarray(outs[1].rgb), np.asarray(outs[0].rgb), atol=1e-5)
    np.testing.assert_allclose(np.asarray(outs[1].alpha), np.asarray(outs[0].alpha), atol=1e-5)
    np.testing.assert_allclose(np.asarray(outs[1].depth), np.asarray(outs[0].depth), atol=1e-5)
    assert 0.2 < float(outs[0].alpha.mean()) < 0.8


def test_2dgs_lowpass_is_a_half_pixel_disc_around_the_projected_centre():
    """``lowpass="2dgs"``: ``ρ = min(u² + v², 2 |c − (x, y)|²)`` (σ² = ½ px²), so a sub-pixel
    surfel shows as ``α = o·exp(−d²)`` at a pixel whose centre is ``d`` pixels from its
    projected centre; without the filter it shows only where a ray hits it (float32)."""
    cam = look_at((0, 0, -2.0), (0, 0, 0), fov_deg=30.0, width=9)
    x = jnp.zeros((1, 3))

    def render(lowpass):
        rend = SurfelRenderer(scale=1e-5, opacity=0.8, lowpass=lowpass, alpha_min=0.0, alpha_max=1.0)
        return np.asarray(jax.jit(rend.render)(x, cam).alpha)

    alpha = {lp: render(lp) for lp in ("2dgs", None)}
    rows, cols = np.mgrid[:9, :9]
    d2 = (rows - 4.0) ** 2 + (cols - 4.0) ** 2  # the origin projects to the centre of pixel (4, 4)
    np.testing.assert_allclose(alpha["2dgs"], 0.8 * np.exp(-d2), atol=1e-6)
    assert alpha[None][4, 4] == pytest.approx(0.8, rel=1e-5)
    assert np.abs(alpha[None][d2 > 0]).max() < 1e-6


@pytest.mark.parametrize("kind", ["surfels", "volume"])
def test_rendering_view_after_view_outside_jit_compiles_once(kind):
    """A pipeline renders one view after the other without a jit of its own: the second view
    (same sizes, another camera, moved particles, a pixel subset as before) reuses the first
    view's programs, and gives what a jitted call gives."""
    x, _ = sphere_particles(0.15, H)
    xj = jnp.asarray(x, jnp.float32)
    rend = (SurfelRenderer if kind == "surfels" else VolumeRenderer).for_particles(np.concatenate([x, x + 0.05]), spacing=H)
    cams = [look_at(eye, (0.0, 0.0, 0.0), fov_deg=40.0, width=24, dtype=jnp.float32)
            for eye in ((0.0, 0.3, -1.5), (1.0, 0.5, -1.0))]
    pixels = np.arange(0, 24 * 24, 3)
    moved = xj + 0.02
    with counting_compilations() as compiles:
        first = (rend.render(xj, cams[0]), rend.silhouette(xj, cams[0], pixels=pixels))
        compiled = len(compiles)
        second = (rend.render(moved, cams[1]), rend.silhouette(moved, cams[1], pixels=pixels))
    assert compiled > 0 and len(compiles) == compiled  # nothing new for the second view
    assert float(first[0].alpha.sum()) > 20 and float(second[1].sum()) > 5
    np.testing.assert_allclose(np.asarray(second[0].rgb), np.asarray(jax.jit(rend.render)(moved, cams[1]).rgb), atol=1e-6)

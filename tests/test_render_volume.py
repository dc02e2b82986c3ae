"""Voxel volume renderer: projected areas, placement, dtype, chunking, gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmpm.errors import ObservationError
from jaxmpm.render import VolumeRenderer, look_at

H = 0.03  # particle spacing of the test sphere
R = 0.3  # its radius


def sphere_particles(radius, h, centre=(0.0, 0.0, 0.0)):
    """Lattice points of spacing h inside a sphere, and the radius of the volume they fill."""
    n = int(np.ceil(radius / h)) + 1
    g = np.arange(-n, n + 1) * h
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    x = x[np.linalg.norm(x, axis=1) < radius]
    r_eff = (3.0 * x.shape[0] * h**3 / (4.0 * np.pi)) ** (1.0 / 3.0)
    return x + np.asarray(centre), r_eff


def projected_sphere(cam, centre, radius):
    """Exact perspective image of a sphere: (area in px², centre of the ellipse in px).

    The silhouette is the conic ``pᵀQp = 0``, ``p = (x̃, ỹ, 1)`` normalised image
    coordinates, ``Q = ĉĉᵀ − cos²θ I`` with ``sin θ = r/|c|`` (the tangent cone).
    """
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
    centre_px = (K @ np.append(x0, 1.0))[:2]
    return area, centre_px


def alpha_centroid(alpha):
    a = np.asarray(alpha, np.float64)
    rows, cols = np.mgrid[: a.shape[0], : a.shape[1]]
    return np.array([(a * (cols + 0.5)).sum(), (a * (rows + 0.5)).sum()]) / a.sum()


@pytest.mark.x64
def test_projected_sphere_formula_centred():
    cam = look_at((0, 0, -2.0), (0, 0, 0), fov_deg=40.0, width=64, dtype=jnp.float64)
    area, c = projected_sphere(cam, (0, 0, 0), 0.3)
    f = float(cam.K[0, 0])
    assert area == pytest.approx(np.pi * (f * 0.3 / np.sqrt(2.0**2 - 0.3**2)) ** 2, rel=1e-12)
    np.testing.assert_allclose(c, [32.0, 32.0], atol=1e-12)


@pytest.fixture(scope="module")
def sphere_scene():
    x, r_eff = sphere_particles(R, H)
    cam = look_at((0.0, 0.0, -2.0), (0.0, 0.0, 0.0), fov_deg=40.0, width=64, dtype=jnp.float32)
    # off-centre: a sphere up-right in the image, seen obliquely
    off = np.array([0.35, -0.25, 0.2])
    return x, r_eff, cam, off


def test_volume_sphere_area_depth_colour(sphere_scene):
    x, r_eff, cam, off = sphere_scene
    rend = VolumeRenderer.for_particles(np.concatenate([x, x + off]), spacing=H)
    render = jax.jit(rend.render)
    out = render(jnp.asarray(x, jnp.float32), cam)
    assert out.rgb.shape == (64, 64, 3) and out.alpha.shape == (64, 64) and out.depth.shape == (64, 64)
    assert out.rgb.dtype == jnp.float32
    area, _ = projected_sphere(cam, (0, 0, 0), r_eff)
    assert float(out.alpha.sum()) == pytest.approx(area, rel=0.05)
    # depth at the centre: the front of the sphere, within a voxel
    assert float(out.depth[32, 32]) == pytest.approx(2.0 - r_eff, abs=2 * H)
    np.testing.assert_allclose(np.asarray(out.rgb[32, 32]), [0.85, 0.45, 0.2], atol=1e-3)
    np.testing.assert_allclose(np.asarray(out.rgb[0, 0]), [1.0, 1.0, 1.0], atol=1e-6)
    # an off-centre sphere lands where the camera model says, with the exact ellipse area
    out2 = render(jnp.asarray(x + off, jnp.float32), cam)
    area2, centre2 = projected_sphere(cam, off, r_eff)
    assert float(out2.alpha.sum()) == pytest.approx(area2, rel=0.05)
    np.testing.assert_allclose(alpha_centroid(out2.alpha), centre2, atol=0.5)
    assert np.all(np.abs(centre2 - 32.0) > 8.0)


@pytest.mark.x64
def test_volume_pixel_subsets_chunks_and_dtype():
    x, _ = sphere_particles(0.2, 0.05)
    cam = look_at((0.5, 0.4, -1.5), (0, 0, 0), fov_deg=25.0, width=20, height=16, dtype=jnp.float32)
    colors = jax.random.uniform(jax.random.key(1), (x.shape[0], 3), jnp.float64)
    # 320 pixels in chunks of 37 (the last one padded) vs 5 pixels in one chunk
    rend = VolumeRenderer.for_particles(x, spacing=0.05, chunk_size=37)
    x64 = jnp.asarray(x, jnp.float64)
    full = jax.jit(rend.render)(x64, cam, colors)  # a float32 camera is cast to the positions' dtype
    assert full.rgb.dtype == jnp.float64 and full.alpha.shape == (16, 20)
    assert 0.1 < float(full.alpha.mean()) < 0.9
    pix = jnp.asarray([3, 150, 171, 319, 160], jnp.int32)
    part = jax.jit(lambda p: rend.render(x64, cam, colors, pixels=p))(pix)
    assert part.rgb.shape == (5, 3) and part.depth.shape == (5,)
    np.testing.assert_allclose(np.asarray(part.rgb), np.asarray(full.rgb).reshape(-1, 3)[pix], atol=1e-12)
    np.testing.assert_allclose(np.asarray(part.alpha), np.asarray(full.alpha).reshape(-1)[pix], atol=1e-12)
    np.testing.assert_allclose(np.asarray(part.depth), np.asarray(full.depth).reshape(-1)[pix], atol=1e-12)


def test_volume_density_mode_and_validation():
    x, _ = sphere_particles(0.2, 0.05)
    cam = look_at((0, 0, -1.5), (0, 0, 0), fov_deg=40.0, width=16, dtype=jnp.float32)
    lev = VolumeRenderer.for_particles(x, spacing=0.05)
    den = VolumeRenderer.for_particles(x, spacing=0.05, mode="density")
    a = np.asarray(jax.jit(lev.silhouette)(jnp.asarray(x, jnp.float32), cam)) > 0.5
    b = np.asarray(jax.jit(den.silhouette)(jnp.asarray(x, jnp.float32), cam)) > 0.5
    # PAC-NeRF-like absorption sees the blurred occupancy's tail: a larger silhouette
    assert a.sum() > 10 and (a & b).sum() == a.sum() and b.sum() > a.sum()
    with pytest.raises(ObservationError, match="mode"):
        VolumeRenderer.for_particles(x, spacing=0.05, mode="nerf")
    with pytest.raises(ObservationError, match=r"\(N, 3\)"):
        lev.render(jnp.zeros((5, 2), jnp.float32), cam)
    with pytest.raises(ObservationError, match="colors"):
        lev.render(jnp.zeros((5, 3), jnp.float32), cam, jnp.zeros((4, 3), jnp.float32))


def test_estimate_spacing_uses_first_frame_of_a_trajectory():
    from jaxmpm.render import estimate_spacing

    x, _ = sphere_particles(0.2, 0.05)
    traj = np.stack([x, x + 0.001])  # frames close together must not look like neighbours
    assert estimate_spacing(x) == pytest.approx(0.05)
    assert estimate_spacing(traj) == pytest.approx(0.05)
    rend = VolumeRenderer.for_particles(traj)
    assert rend.dx == pytest.approx(0.05) and rend.particle_volume == pytest.approx(0.05**3)

"""Image losses: values, gradients against finite differences, a small fit, observation
helpers (render_views, tile_views, write_video) and size checks."""

import imageio.v2 as imageio
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from jaxmpm.errors import ObservationError
from jaxmpm.render import (
    SurfelRenderer,
    VolumeRenderer,
    gather_pixels,
    masked_rgb_l2,
    pacnerf_rig,
    render_pixels,
    render_views,
    rgb_loss,
    sample_pixels,
    silhouette_l2,
    silhouette_loss,
    soft_iou_loss,
    tile_views,
    write_video,
)


def sphere_particles(radius, h, centre=(0.0, 0.0, 0.0)):
    n = int(np.ceil(radius / h)) + 1
    g = np.arange(-n, n + 1) * h
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    return x[np.linalg.norm(x, axis=1) < radius] + np.asarray(centre)


def make_renderer(kind, x, h):
    cls = VolumeRenderer if kind == "volume" else SurfelRenderer
    # a box margin wide enough for the perturbed / moving spheres below
    return cls.for_particles(x, spacing=h, **({"margin": 4.0} if kind == "volume" else {}))


def test_sample_pixels_and_pointwise_losses():
    pix = sample_pixels(jax.random.key(0), 3, 5, 7, 20)
    assert pix.shape == (3, 20) and pix.dtype == jnp.int32
    p = np.asarray(pix)
    assert p.min() >= 0 and p.max() < 35 and all(len(set(row)) == 20 for row in p)
    assert not np.array_equal(p[0], p[1])
    with pytest.raises(ObservationError, match="distinct pixels"):
        sample_pixels(jax.random.key(0), 1, 4, 4, 17)
    img = jnp.arange(3 * 5 * 7, dtype=jnp.float32).reshape(3, 5, 7)
    expect = np.take_along_axis(np.asarray(img).reshape(3, -1), p, axis=1)
    np.testing.assert_array_equal(np.asarray(gather_pixels(img, pix)), expect)
    a = jnp.asarray([0.0, 1.0, 1.0, 0.0], jnp.float32)
    assert float(silhouette_l2(a, a)) == 0.0
    assert float(soft_iou_loss(a, a)) == pytest.approx(0.0, abs=1e-6)
    assert float(soft_iou_loss(a, 1.0 - a)) == pytest.approx(1.0)
    assert float(silhouette_l2(a, 1.0 - a)) == 1.0


@pytest.mark.x64
@pytest.mark.parametrize("kind", ["volume", "surfels"])
def test_image_loss_gradients_match_finite_differences(kind):
    h = 0.05
    # jittered lattice: no exact ties in the surfels' depth order (the sort makes colour
    # piecewise constant in the order) and no particle on a voxel node (a kink of the
    # trilinear weights)
    x0 = sphere_particles(0.2, h)
    x0 = x0 + np.random.default_rng(0).uniform(-0.3 * h, 0.3 * h, x0.shape)
    cams = pacnerf_rig(2, radius=1.2, fov_deg=40.0, res=16, dtype=jnp.float64)
    rend = make_renderer(kind, x0, h)
    n = x0.shape[0]
    colors = jax.random.uniform(jax.random.key(1), (n, 3), jnp.float64)
    shifted = jnp.asarray(x0 + np.array([0.04, -0.03, 0.02]), jnp.float64)

    @jax.jit
    def targets(x):
        out = jax.vmap(lambda c: rend.render(x, c, colors))(cams)
        return out.alpha, out.rgb

    masks, images = targets(shifted)
    pixels = sample_pixels(jax.random.key(2), 2, 16, 16, 100)

    tmask = gather_pixels(masks, pixels)
    timg = gather_pixels(images, pixels)

    def loss(x):
        out = render_pixels(rend, x, cams, pixels, colors)  # one render for three losses
        return (
            silhouette_l2(out.alpha, tmask)
            + 0.5 * soft_iou_loss(out.alpha, tmask)
            + masked_rgb_l2(out.rgb, timg, tmask)
        )

    f = jax.jit(jax.value_and_grad(loss))  # one compiled function for AD and FD values
    x = jnp.asarray(x0, jnp.float64)
    value, grad = f(x)
    assert np.all(np.isfinite(np.asarray(grad))) and float(value) > 1e-4
    v = jax.random.normal(jax.random.key(3), x.shape, jnp.float64)
    eps = 1e-6
    fd = (float(f(x + eps * v)[0]) - float(f(x - eps * v)[0])) / (2 * eps)
    ad = float(jnp.sum(grad * v))
    assert abs(ad) > 1e-3
    assert ad == pytest.approx(fd, rel=1e-4, abs=1e-7)


@pytest.mark.parametrize("kind", ["volume", "surfels"])
def test_silhouette_fit_moves_sphere_to_target(kind):
    h = 0.05
    x0 = sphere_particles(0.25, h)
    cams = pacnerf_rig(3, radius=1.0, fov_deg=40.0, res=24, dtype=jnp.float32)
    rend = make_renderer(kind, x0, h)
    offset = jnp.asarray([0.08, -0.06, 0.07], jnp.float32)
    base = jnp.asarray(x0, jnp.float32)
    masks = jax.jit(jax.vmap(lambda c: rend.silhouette(base + offset, c)))(cams)
    masks = (np.asarray(masks) > 0.5).astype(np.uint8) * 255  # an observation: 0/255 masks
    opt = optax.adam(0.01)

    @jax.jit
    def step(delta, state, key):
        pixels = sample_pixels(key, 3, 24, 24, 288)  # half of the pixels, fresh each step
        loss, g = jax.value_and_grad(lambda d: silhouette_loss(rend, base + d, cams, masks, pixels))(delta)
        with jax.numpy_dtype_promotion("standard"):  # optax's Adam mixes int and float
            upd, state = opt.update(g, state, delta)
        return optax.apply_updates(delta, upd), state, loss

    delta = jnp.zeros(3, jnp.float32)
    state = opt.init(delta)
    losses = []
    for i in range(30):
        delta, state, loss = step(delta, state, jax.random.key(i))
        losses.append(float(loss))
    err = float(jnp.linalg.norm(delta - offset))
    assert err < 0.02, (err, np.asarray(delta), losses[::5])
    assert losses[-1] < 0.25 * losses[0]


def test_size_mismatch_and_view_count_raise():
    x = jnp.asarray(sphere_particles(0.2, 0.05), jnp.float32)
    cams = pacnerf_rig(2, radius=1.2, res=16)
    rend = VolumeRenderer.for_particles(np.asarray(x), spacing=0.05)
    with pytest.raises(ObservationError, match=r"image size \(H, W\) = \(16, 12\)"):
        silhouette_loss(rend, x, cams, np.zeros((2, 16, 12), np.uint8))
    with pytest.raises(ObservationError, match="2 views"):
        silhouette_loss(rend, x, cams, np.zeros((3, 16, 16), np.uint8))
    with pytest.raises(ObservationError, match="target images"):
        rgb_loss(rend, x, cams, np.zeros((2, 16, 16), np.uint8))
    with pytest.raises(ObservationError, match="kind"):
        silhouette_loss(rend, x, cams, np.zeros((2, 16, 16), np.uint8), kind="dice")


def test_render_views_tiles_and_video(tmp_path):
    h = 0.05
    x = sphere_particles(0.2, h)
    traj = np.stack([x, x + np.array([0.0, -0.1, 0.0])]).astype(np.float32)  # (T=2, N, 3)
    cams = pacnerf_rig(3, radius=1.0, fov_deg=30.0, res=(20, 16))
    colors = np.tile(np.array([[0.2, 0.4, 0.9]], np.float32), (x.shape[0], 1))
    obs = render_views(traj, cams, "volume", colors, spacing=h)
    assert obs["masks"].shape == (3, 2, 16, 20) and obs["masks"].dtype == np.uint8
    assert obs["images"].shape == (3, 2, 16, 20, 3) and obs["images"].dtype == np.uint8
    assert obs["intrinsics"].shape == (3, 3, 3) and obs["cam_to_world"].shape == (3, 4, 4)
    assert set(np.unique(obs["masks"])) == {0, 255}
    assert obs["images"][obs["masks"] == 0].mean() > 245  # white background
    inside = obs["images"][obs["masks"] == 255]
    assert np.abs(inside.mean(0) - np.array([51, 102, 230])).max() < 25
    # the sphere moves down: its mask's mean row grows in every view
    rows = np.arange(16)[None, None, :, None]
    mean_row = (obs["masks"] * rows).sum((2, 3)) / obs["masks"].sum((2, 3))
    assert np.all(mean_row[:, 1] > mean_row[:, 0])
    surf = render_views(traj[:1], cams, "surfels", spacing=h)
    a, b = obs["masks"][:, 0] > 0, surf["masks"][:, 0] > 0
    assert (a & b).sum() / (a | b).sum() > 0.8  # a coarse sphere (2 voxels in radius)
    tiled = tile_views(obs["images"], pad=1)
    assert tiled.shape == (2, 2 * 17 - 1, 2 * 21 - 1, 3)
    np.testing.assert_array_equal(tiled[:, 17:33, 0:20], obs["images"][2])
    mp4 = write_video(tmp_path / "v.mp4", tiled, fps=4)
    assert mp4.exists() and mp4.stat().st_size > 0
    gif = write_video(tmp_path / "v.gif", tiled, fps=4)
    assert len(imageio.mimread(gif)) == 2
    with pytest.raises(ObservationError, match="renderer"):
        render_views(traj, cams, "nerf")

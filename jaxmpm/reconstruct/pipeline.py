"""``identify``: from a PAC-NeRF-layout folder to a scene, fitted parameters and a report.

Stages (each callable alone): :func:`jaxmpm.reconstruct.read_dataset` →
:func:`scene_skeleton` (the hint plus stated defaults) →
:func:`jaxmpm.reconstruct.check_cameras` (each view against the others' visual hull) →
:func:`reconstruct_body` →
:func:`reconstruct_colliders` → :func:`write_scene` → :func:`identify_material` (the one
call of :func:`jaxmpm.fit`) → :func:`simulated_masks` (IoU over time) → :func:`write_report`.
:func:`identify` runs them all; it writes into a staging folder beside the output folder and
moves the files in only when every stage has succeeded.
"""

from __future__ import annotations

import copy
import json
import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import ObservationError
from ..fit_report import format_value, numerics_cells, numerics_columns
from ..identify.residuals import frames_needed, observation_cameras
from ..render import tile_views
from .calibration import MIN_IOU_GAIN, ViewOffsets, check_cameras
from .collider import Surfels, fit_surfels, hull_mesh, roof_height
from .dataset import Dataset, read_dataset
from .free_fall import AREA_NOISE_LIMIT, FreeFall, free_fall
from .hull import Hull, hull_particles, silhouette_iou, visual_hull
from .refine import BodyRefinement, refine_body

#: Defaults for what a hint does not give (docs/identify.md states them).
DEFAULT_PPC = 8
DEFAULT_CELLS = 32  # dx = longest domain side / DEFAULT_CELLS
DEFAULT_GRAVITY = (0.0, -9.8, 0.0)
DEFAULT_DENSITY = 1000.0
#: Default substeps: dt = dx / SUBSTEP_SPEED (the speed of sound of the default guesses,
#: about 10 m/s, with a margin of 5).
SUBSTEP_SPEED = 50.0
#: Renderer of the re-projected silhouettes (IoU, overlay video): surfels need no grid, so a
#: body's silhouette does not depend on the bounds of the positions rendered with it.
RENDERER = "surfels"
#: Body particles allowed inside the colliders' hull (a fraction) before it is an error.
MAX_OVERLAP = 0.02


@dataclass
class Reconstruction:
    """What :func:`reconstruct` recovers from the views.

    Attributes:
        spec: the scene spec (DESIGN §5.1) with the body as ``points`` (path ``body.npy``)
            and the colliders (hint planes, then the reconstructed one as ``collider_disks.npz``
            or ``collider.obj``).
        points: ``(N, 3)`` body particles, m.
        body_hull: the body's visual hull.
        body_iou: ``(V,)`` first-frame IoU between observed and re-rendered silhouettes.
        collider_mesh: marching-cubes mesh of the collider hull (``trimesh.Trimesh``) or None.
        surfels: fitted collider surfels or None.
        collider: which reconstructed collider the scene uses: ``"disks"``, ``"mesh"`` or None.
        free_fall: the free-fall analysis of the silhouettes (:func:`free_fall`): the body's
            starting velocity guess, and the gravity when the hint gives none.
        collider_roof: ``(height m, lowest view's elevation degrees)``: how high a roof the
            views may have left on the collider's top (:func:`roof_height`), or None.
        refinement: the first-frame refinement (:func:`refine_body`; ``points`` and
            ``body_iou`` are then the refined ones), or None.
    """

    spec: dict
    points: np.ndarray
    body_hull: Hull
    body_iou: np.ndarray
    collider_mesh: object | None = None
    surfels: Surfels | None = None
    collider: str | None = None
    free_fall: FreeFall | None = None
    collider_roof: tuple[float, float] | None = None
    refinement: BodyRefinement | None = None


#: Free-fall frames needed before the silhouettes' gravity replaces the default: a parabola
#: passes through any 3 centres, so the 4th is the first check that the body fell freely.
GRAVITY_FRAMES = 4


def _optical_center(K: np.ndarray, c2w: np.ndarray) -> tuple[np.ndarray, float]:
    """The point nearest to all optical axes and the half-side of a cube around it that
    every camera sees whole, m."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for P in c2w:
        d = P[:3, 2] / np.linalg.norm(P[:3, 2])
        M = np.eye(3) - np.outer(d, d)
        A += M
        b += M @ P[:3, 3]
    center = np.linalg.solve(A, b)
    half = min(
        float((center - P[:3, 3]) @ P[:3, 2]) * min(k[0, 2] / k[0, 0], k[1, 2] / k[1, 1]) / math.sqrt(3.0)
        for k, P in zip(K, c2w)
    )
    return center, half


def scene_skeleton(dataset: Dataset, material: str) -> dict:
    """The scene spec without bodies: the hint's keys, and stated defaults for the rest.

    Defaults: ``domain`` the cube around the point nearest to all optical axes that every
    camera sees whole (extended down to a hint floor); ``dx`` = its longest side /
    :data:`DEFAULT_CELLS`; ``gravity`` (0, −9.8, 0); ``frame_dt`` from the ``time`` values;
    ``frames`` to cover the last observed time; ``substeps`` so that dt = dx / 50 m/s;
    ``collision = "cpic"``; ``flip`` 0 (APIC); the material's starting guess PAC-NeRF's (each
    parameter's declared ``guess``), density 1000 kg/m³, ``ppc`` 8.
    """
    from ..constitutive import MATERIALS

    if material not in MATERIALS:
        raise ObservationError(f"unknown material {material!r}; expected one of {', '.join(sorted(MATERIALS))}")
    hint = copy.deepcopy(dataset.hint)
    obs = dataset.observation
    spec: dict = {"dim": 3}
    if "domain" in hint:
        lo, hi = np.asarray(hint["domain"]["lo"], float), np.asarray(hint["domain"]["hi"], float)
    else:
        c, half = _optical_center(np.asarray(obs.intrinsics, float), np.asarray(obs.cam_to_world, float))
        lo, hi = c - half, c + half
        for plane in hint.get("colliders", []):
            n = np.asarray(plane["normal"], float)
            axis = int(np.argmax(np.abs(n)))
            if np.allclose(np.abs(n) / np.linalg.norm(n), np.eye(3)[axis]):
                p = float(plane["point"][axis])
                lo[axis] = min(lo[axis], p) if n[axis] > 0 else lo[axis]
                hi[axis] = max(hi[axis], p) if n[axis] < 0 else hi[axis]
    dx = float(hint.get("dx", float(np.max(hi - lo)) / DEFAULT_CELLS))
    spec["dx"] = dx
    spec["domain"] = {"lo": [float(v) for v in lo], "hi": [float(v) for v in hi]}
    spec["gravity"] = [float(g) for g in hint.get("gravity", DEFAULT_GRAVITY)]
    spec["frame_dt"] = dataset.frame_dt
    spec["frames"] = int(round(float(obs.times[-1]) / dataset.frame_dt)) + 1
    if "substeps" in hint or "dt" in hint:
        spec.update({k: hint[k] for k in ("substeps", "dt") if k in hint})
    else:
        spec["substeps"] = max(1, math.ceil(dataset.frame_dt * SUBSTEP_SPEED / dx))
    spec["collision"] = hint.get("collision", "cpic")
    if "flip" in hint:
        spec["flip"] = float(hint["flip"])
    spec["colliders"] = [dict(c, name=c.get("name", f"plane{k}")) for k, c in enumerate(hint.get("colliders", []))]
    return spec


def body_material(dataset: Dataset, material: str) -> tuple[dict, int, str]:
    """``(material table, ppc, name)`` of the body: the hint's, else the stated defaults."""
    from ..constitutive import MATERIALS

    body = (dataset.hint.get("bodies") or [{}])[0]
    table = dict(body.get("material", {}))
    if table.get("model", material) != material:
        raise ObservationError(f"scene hint: bodies[0].material.model is {table['model']!r} but --material is {material!r}")
    if material not in MATERIALS:
        raise ObservationError(f"--material {material!r}: unknown model; expected one of {', '.join(sorted(MATERIALS))}")
    cls = MATERIALS[material]
    guess = {p.name: p.guess for p in cls.parameters if p.name in cls.required() and p.guess is not None}
    table = {"model": material, "density": DEFAULT_DENSITY, **guess, **table}
    return table, int(body.get("ppc", DEFAULT_PPC)), str(body.get("name", "body"))


def particle_spacing(spec: dict, ppc: int) -> float:
    """The body lattice's spacing, m: ``dx / ppc^(1/3)``."""
    return float(spec["dx"]) / ppc ** (1.0 / 3.0)


#: Views needed before :func:`reconstruct_body` tries a hull that lets one view disagree.
AUTO_TOLERANCE_VIEWS = 4
#: First-frame mean IoU a hull with k = 1 must gain over k = 0 to be used: the gain the cameras'
#: check asks of a view's offset.
AUTO_TOLERANCE_GAIN = MIN_IOU_GAIN


def reconstruct_body(
    dataset: Dataset, spec: dict, *, ppc: int = DEFAULT_PPC, tolerance: int | None = None, voxel: float | None = None
) -> tuple[np.ndarray, Hull, np.ndarray]:
    """Body particles from the first frame's masks, and the re-projection IoU.

    Arguments:
        dataset: the dataset.
        spec: the scene skeleton (its ``domain`` bounds the hull, its ``dx`` sets the lattice).
        ppc: particles per cell (lattice spacing ``dx / ppc^(1/3)``).
        tolerance: k of the visual hull (a voxel is kept when ≥ V − k views see it inside).
            ``None`` (default) chooses: with at least :data:`AUTO_TOLERANCE_VIEWS` views, k = 1
            when its particles' silhouettes match the first frame's masks better (mean IoU
            higher by :data:`AUTO_TOLERANCE_GAIN`), else k = 0. Consistent masks reproject
            best from k = 0 (measured on the six-view drop data: mean IoU 0.975–0.996 against
            0.882–0.925 with k = 1); masks whose borders are each off by a pixel or two carve
            k = 0's intersection too small (0.730 against 0.786; docs/identify.md §4).
        voxel: hull voxel edge, m (default the particle spacing: finer voxels resolve the
            few-view hull's excess corners, which then add particles; measured on the tiny
            test dataset: first-frame IoU 0.94–0.97 at spacing/2, 0.96–1.0 at spacing).

    Returns:
        ``(points (N, 3), hull, iou (V,))``; IoU between each view's first-frame mask and the
        silhouette of the points (:data:`RENDERER`). ``hull.tolerance`` is the k used.

    Raises:
        ObservationError: an empty hull (the views' first masks share no point in the domain).
    """
    obs = dataset.observation
    views = obs.masks.shape[0]
    spacing = particle_spacing(spec, ppc)
    voxel = spacing if voxel is None else float(voxel)
    choices = [0, 1] if tolerance is None and views >= AUTO_TOLERANCE_VIEWS else [tolerance or 0]
    hull = visual_hull(obs.masks[:, 0], obs.intrinsics, obs.cam_to_world, spec["domain"]["lo"], spec["domain"]["hi"],
                       voxel, tolerance=choices[0])
    best = None
    for k in choices:
        candidate = hull.with_tolerance(k)
        points = hull_particles(candidate, spacing)
        if len(points) == 0:
            continue
        iou = _first_frame_iou(points, obs, spacing)
        if best is None or iou.mean() >= best[2].mean() + AUTO_TOLERANCE_GAIN:
            best = (points, candidate, iou)
    if best is None:
        raise ObservationError(
            f"{dataset.folder}: the first frame's visual hull is empty: no point of the domain "
            f"{spec['domain']} is inside {views - choices[-1]} of the views' masks (check the cameras and masks)"
        )
    return best


def _first_frame_iou(points: np.ndarray, obs, spacing: float) -> np.ndarray:
    """``(V,)`` IoU of each view's first-frame mask with the silhouette of ``points``."""
    from ..render import render_views

    rendered = render_views(points[None].astype(np.float32), observation_cameras(obs), RENDERER, spacing=spacing)
    return silhouette_iou(rendered["masks"][:, 0], obs.masks[:, 0])


#: The collider hull's voxel edge, in cells (dx). Measured on the 0.2 m bunny (dx = 0.05 m,
#: 6 views of 96 px; docs/identify.md §4): identification from the hull's mesh at dx / 2
#: missed μ by 0.13 decades, at dx / 10 by 0.009 (the truth imported: 0.050).
#: The surfels are fitted from the dx / 2 hull's mesh: snapped onto the fine hull's one-voxel
#: staircase their normals tilt (silhouette IoU 0.87-0.94 per view on the tests' box, against
#: 0.92-0.96), and Taubin smoothing, which mends that, rounds a box's edges (then μ on the edge
#: of a box came out 0.09 decades off from the mesh, 0.37 from the surfels).
COLLIDER_VOXEL = 0.1


def reconstruct_colliders(
    dataset: Dataset,
    spec: dict,
    points: np.ndarray,
    *,
    surfels: bool = True,
    surfel_count: int = 600,
    surfel_steps: int = 80,
    voxel: float | None = None,
    rgb: float = 0.0,
    progress: Callable[[int, float], None] | None = None,
):
    """The collider from ``data/c_{view}.png``: hull → mesh, and (``surfels``) fitted surfels.

    The hull is carved twice: over the domain at dx / 2 to find the collider, then at ``voxel``
    (default :data:`COLLIDER_VOXEL` × dx) over the collider's box. The mesh returned is the fine
    hull's; the surfels are fitted from the coarse one's, to the collider masks and snapped onto
    that hull or, when ``rgb`` > 0, also to the plates' colours inside the masks with that
    weight and left where the colours put them (:func:`fit_surfels`; measured on a painted box
    seen from 12 views, the lowest 15° up: the surfels' roof over the top 7 mm against the
    hull's 27 mm, an elastic block rests 0.78 dx above where it rests on the true box against
    1.15 dx; from 6 views the colours hardly help: roof 20 mm, docs/identify.md §3).

    Returns ``(hull, mesh, surfels)`` (surfels None when not asked), or ``(None, None, None)``
    when the dataset has no collider masks.

    Raises:
        ObservationError: an empty collider hull, or more than :data:`MAX_OVERLAP` of the
            body's particles inside the collider's hull.
    """
    if dataset.collider_masks is None:
        return None, None, None
    obs = dataset.observation
    dx = float(spec["dx"])
    voxel = COLLIDER_VOXEL * dx if voxel is None else float(voxel)
    args = (dataset.collider_masks, obs.intrinsics, obs.cam_to_world)
    # a coarse hull over the domain finds the collider; the fine one covers only its box
    coarse = visual_hull(*args, spec["domain"]["lo"], spec["domain"]["hi"], max(voxel, 0.5 * dx))
    if coarse.occupied.any():
        ijk = np.argwhere(coarse.occupied)
        lo = np.maximum(coarse.lo + (ijk.min(axis=0) - 1) * coarse.voxel, spec["domain"]["lo"])
        hi = np.minimum(coarse.lo + (ijk.max(axis=0) + 2) * coarse.voxel, spec["domain"]["hi"])
        hull = visual_hull(*args, lo, hi, voxel)
    else:
        hull = coarse
    inside = hull.contains(points)
    if inside.mean() > MAX_OVERLAP:
        raise ObservationError(
            f"{dataset.folder}: the colliders (data/c_*.png) overlap the body: {inside.mean():.0%} of the first "
            "frame's body lies inside the collider hull"
        )
    mesh = hull_mesh(hull)  # raises on an empty hull
    fitted = None
    if surfels:  # on the coarse hull's mesh: see COLLIDER_VOXEL
        fitted = fit_surfels(hull_mesh(coarse), dataset.collider_masks, obs.intrinsics, obs.cam_to_world,
                             count=surfel_count, steps=surfel_steps, images=dataset.plates if rgb > 0 else None,
                             rgb_weight=rgb, snap=rgb == 0, progress=progress)
    return hull, mesh, fitted


def reconstruct(
    dataset: Dataset,
    material: str,
    *,
    tolerance: int | None = None,
    collider: str = "mesh",
    surfels: bool = True,
    surfel_count: int = 600,
    surfel_steps: int = 80,
    refine: int = 0,
    collider_rgb: float = 0.0,
    progress: Callable[[int, float], None] | None = None,
) -> Reconstruction:
    """Body and colliders from the views, as a scene spec (nothing is written).

    Arguments:
        dataset: from :func:`read_dataset`.
        material: the material model name (``newtonian``, ``sand``, …).
        tolerance: k of the body's visual hull (``None``: chosen, see :func:`reconstruct_body`).
        collider: the reconstructed collider the scene uses: ``"mesh"`` (the hull's
            marching-cubes mesh, the default) or ``"disks"`` (the fitted surfels, AS-DiffMPM's;
            both are always reconstructed). Measured (docs/identify.md §4): on the edge of a
            box μ is found within 0.006 decades from the mesh and 0.05–0.06 from the surfels; on
            the 0.2 m bunny within 0.009 from the mesh and 0.24–0.56 off from the surfels
            (surfels placed on the true bunny: 0.44 off) — CPIC's disk field is the weak part.
        surfels: fit the surfels (needed for ``collider="disks"``).
        surfel_count, surfel_steps: surfels placed and Adam steps.
        refine: Adam steps of the first-frame refinement (:func:`refine_body`, on the masks
            and the RGB of the first frame); 0 (default) keeps the hull's particles.
        collider_rgb: weight of the background plates' colours in the surfel fit
            (:func:`fit_surfels`; needs frame −1 in every view); 0 (default): masks only.
        progress: ``progress(step, loss)`` of the refinement and the surfel fit.
    """
    if collider not in ("disks", "mesh"):
        raise ObservationError(f"collider must be 'disks' or 'mesh', got {collider!r}")
    if collider == "disks" and not surfels:
        raise ObservationError("collider='disks' needs the surfels (surfels=True)")
    if isinstance(refine, bool) or not isinstance(refine, (int, np.integer)) or refine < 0:
        raise ObservationError(f"refine (Adam steps) must be an integer >= 0, got {refine!r}")
    _check_rgb_weight(collider_rgb, dataset.plates,
                      f"{dataset.folder}: a collider RGB weight needs a background plate data/r_{{view}}_-1.png in every view")
    spec = scene_skeleton(dataset, material)
    table, ppc, name = body_material(dataset, material)
    points, hull, iou = reconstruct_body(dataset, spec, ppc=ppc, tolerance=tolerance)
    refined = None
    if refine > 0:
        obs = dataset.observation
        first_rgb = None if obs.images is None else obs.images[:, 0]
        refined = refine_body(points, obs.masks[:, 0], obs.intrinsics, obs.cam_to_world, particle_spacing(spec, ppc),
                              images=first_rgb, steps=refine, progress=progress)
        points, iou = refined.points, refined.iou_after
    _check_floors(points, spec["colliders"], dataset.folder)
    _, mesh, surf = reconstruct_colliders(dataset, spec, points, surfels=surfels, surfel_count=surfel_count,
                                          surfel_steps=surfel_steps, rgb=collider_rgb, progress=progress)
    spec["bodies"] = [{"shape": "points", "path": "body.npy", "ppc": ppc, "name": name, "material": table}]
    obs = dataset.observation
    fall = free_fall(obs.masks, observation_cameras(obs), np.asarray(obs.times), spec["dx"], gravity=spec["gravity"])
    if fall.velocity is not None:
        spec["bodies"][0]["velocity"] = [float(v) for v in fall.velocity]
    if "gravity" not in dataset.hint and fall.gravity is not None and fall.frames >= GRAVITY_FRAMES:
        spec["gravity"] = [float(g) for g in fall.gravity]
    used, roof = None, None
    if mesh is not None:
        roof = roof_height(mesh, obs.cam_to_world, -np.asarray(spec["gravity"], float))
        used = collider
        entry = {"type": "disks", "path": "collider_disks.npz"} if collider == "disks" else {"type": "mesh", "path": "collider.obj"}
        spec["colliders"].append({**entry, "name": "collider", "contact": "sticky"})
    return Reconstruction(spec=spec, points=points, body_hull=hull, body_iou=iou, collider_mesh=mesh, surfels=surf,
                          collider=used, free_fall=fall, collider_roof=roof, refinement=refined)


def _check_floors(points: np.ndarray, planes: list[dict], folder) -> None:
    for plane in planes:
        n = np.asarray(plane["normal"], float)
        below = (points - np.asarray(plane["point"], float)) @ n < 0
        if below.mean() > MAX_OVERLAP:
            raise ObservationError(f"{folder}: the hint's plane {plane['name']!r} cuts the body: {below.mean():.0%} of it lies behind the plane")


# --------------------------------------------------------------------------- files


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    return "[" + ", ".join(_toml_value(x) for x in v) + "]"


def to_toml(spec: dict) -> str:
    """A scene spec as TOML text (top-level keys, then ``[[bodies]]`` and ``[[colliders]]`` tables)."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in spec.items() if k not in ("bodies", "colliders")]
    for table in ("bodies", "colliders"):
        for item in spec.get(table, []):
            lines += ["", f"[[{table}]]"] + [f"{k} = {_toml_value(v)}" for k, v in item.items()]
    return "\n".join(lines) + "\n"


def write_scene(recon: Reconstruction, out: str | os.PathLike) -> Path:
    """Write ``out/scene.toml``, ``out/body.npy`` and the collider files (``collider.obj``
    always when there is a collider, ``collider_disks.npz`` when surfels were fitted)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    np.save(out / "body.npy", recon.points)
    if recon.collider_mesh is not None:
        recon.collider_mesh.export(out / "collider.obj")
    if recon.surfels is not None:
        recon.surfels.save(out / "collider_disks.npz")
    path = out / "scene.toml"
    path.write_text(to_toml(recon.spec))
    return path


# --------------------------------------------------------------------------- fit and report


def _check_rgb_weight(rgb: float, images, what: str = "an RGB weight needs the frames' colour images") -> None:
    """A weight must be finite and >= 0; a positive one needs ``images`` (``what`` says which)."""
    if isinstance(rgb, bool) or not isinstance(rgb, (int, float, np.number)) or not (np.isfinite(rgb) and rgb >= 0):
        raise ObservationError(f"the RGB weight must be a number >= 0, got {rgb!r}")
    if rgb > 0 and images is None:
        raise ObservationError(what)


def mask_area_noise(observation, dx: float) -> float:
    """Robust σ of the body's silhouette areas from frame to frame (relative;
    :func:`jaxmpm.reconstruct.free_fall.area_noise`, distance-corrected as the free fall's shape
    test) of an observation with 3D masks, cameras and at least 3 frames; NaN otherwise."""
    if observation.masks is None or observation.intrinsics is None or len(observation.times) < 3:
        return float("nan")
    return free_fall(observation.masks, observation_cameras(observation), np.asarray(observation.times), dx).area_noise


def identify_material(scene, observation, names, *, max_steps: int | None = None, num_pixels: int = 256,
                      renderer: str = RENDERER, rgb: float = 0.0, colors="auto", refine_velocity: bool | None = None,
                      numerics: bool = False, progress=None, log=None):
    """Fit ``names`` (material parameters and ``velocity``) to the silhouettes: the one call
    of :func:`jaxmpm.fit` in this package (PAC-NeRF's stages: the velocity from the
    pre-contact frames, then the material, each log10 parameter first scanned over
    :data:`jaxmpm.fit.SCAN_DECADES` from its guess, as ``fit`` does by default for any fit
    without per-particle tracks). Returns a :class:`jaxmpm.FitResult`.

    ``renderer``: the fit's (``"surfels"`` or ``"volume"``). The default is the renderer the
    body was reconstructed against (its first-frame IoU, :data:`RENDERER`): a renderer
    whose silhouette of the same particles is larger is explained by a body that shrinks
    (measured: the volume renderer's silhouettes of the true particles cover 8 % more pixels
    than the surfels' and the fit took kappa from 1e5 to 68 Pa; docs/identify.md).

    ``rgb``: the weight of the masked-RGB term beside the silhouettes' (weight 1; default 0,
    silhouettes only, as GIC); ``colors``: the particles' colours for it (``"auto"``: each
    particle's mean colour in the first frame's views, :func:`jaxmpm.identify.particle_colors`).

    ``refine_velocity``: refit the velocity with the material in the stages after the
    pre-contact one (:attr:`jaxmpm.FitConfig.refine_velocity`). None (default, unlike
    ``fit``'s automatic choice): held where the pre-contact frames put it, except where the
    masks' areas jump from frame to frame by more than
    :data:`jaxmpm.reconstruct.free_fall.AREA_NOISE_LIMIT` (:func:`mask_area_noise`): a
    reconstructed body's shape errors would pass into a refitted velocity (on clean views μ
    0.0003 → 0.036 decades), while an error in the held velocity is absorbed by the material
    (on blurred views μ 0.15 → 0.015 refitted), and with borders that move 1–2 px from frame
    to frame the pre-contact frames put it 0.24 m/s off (the jittered bunny, μ 0.20 held,
    0.096 refitted; docs/identify.md §4). A note says when it is refitted for that reason.

    ``numerics``: also refit the result at dt/2 and with the other transfer
    (:attr:`jaxmpm.FitConfig.numerics`): the parameters' numerical error."""
    from ..fit import SCAN_DECADES, FitConfig, fit

    _check_rgb_weight(rgb, observation.images)
    note = None
    if refine_velocity is None:
        noise = mask_area_noise(observation, float(scene.model.grid.dx))
        refine_velocity = bool(noise > AREA_NOISE_LIMIT)
        if refine_velocity:
            note = (f"the masks' areas jump by {100 * noise:.0f} % (σ) from frame to frame: the velocity is refitted "
                    "with the material (the pre-contact frames alone pin it only to their borders' noise)")
            if log is not None:
                log(note)
    config = FitConfig(max_steps=max_steps, num_pixels=num_pixels, renderer=renderer, scan=SCAN_DECADES,
                       weights={"silhouette": 1.0, "rgb": float(rgb)}, colors=colors,
                       refine_velocity=bool(refine_velocity), numerics=numerics)
    result = fit(scene.model, scene.params, observation, names, config, progress=progress, log=log)
    if note is not None:
        result.notes.insert(0, note)
    return result


#: How often :func:`simulated_masks` may halve dt when the rollout is unhealthy (as ``fit``'s
#: ``max_dt_halvings``).
EVALUATION_HALVINGS = 3


def simulated_masks(scene, params, observation, substeps: int | None = None, *,
                    notes: list[str] | None = None) -> np.ndarray:
    """Silhouettes ``(V, T, H, W)`` uint8 of a rollout with ``params`` at the observed times
    (:data:`RENDERER`, the observation's cameras; ``substeps`` per frame, default the scene's).

    The rollout is :func:`jaxmpm.simulate`'s without checkpoints (the compilation the fit's
    contact detection made). An unhealthy one is repeated with dt halved, up to
    :data:`EVALUATION_HALVINGS` times (:func:`jaxmpm.step.simulate_healthy`), and a line saying
    so is appended to ``notes``: a fit's health checks ran at points a float32 round trip away
    from its result, and a rollout near an instability can fall either side (measured: a
    Newtonian fit on jittered masks whose result, re-simulated, reached CFL 1.16 in the last
    frame)."""
    from ..render import render_views
    from ..step import simulate_healthy

    model = scene.model if substeps is None else scene.model.with_substeps(int(substeps))
    frames = frames_needed(model, np.asarray(observation.times, float))
    traj, model, discarded = simulate_healthy(model, params, halvings=EVALUATION_HALVINGS, frames=frames)
    if notes is not None and discarded:
        notes.append(f"the evaluation rollout was unhealthy at {' and at '.join(discarded)}; evaluated at "
                     f"{model.substeps} substeps per frame")
    idx = np.round(np.asarray(observation.times) / model.frame_dt).astype(int)
    x = np.asarray(traj.x)[idx]
    spacing = float(np.cbrt(np.asarray(model.bodies[0].vol0)[0]))
    return render_views(x, observation_cameras(observation), RENDERER, spacing=spacing)["masks"]


def overlay_frames(observed: np.ndarray, simulated: np.ndarray, views: int = 4) -> np.ndarray:
    """Video frames ``(T, H', W', 3)`` uint8: observed silhouettes in red, simulated in green
    (overlap yellow), the first ``views`` views side by side."""
    V = min(views, observed.shape[0])
    rgb = np.zeros(observed[:V].shape + (3,), np.uint8)
    rgb[..., 0] = observed[:V]
    rgb[..., 1] = simulated[:V]
    return tile_views(rgb, cols=V, pad=2)


def overlay_sheet(observed: np.ndarray, simulated: np.ndarray, views: int = 4, frames: int = 6) -> np.ndarray:
    """One picture ``(H', W', 3)`` uint8 of :func:`overlay_frames`: up to ``frames`` frames,
    evenly spaced from the first to the last, one per row (2 px white lines between rows)."""
    video = overlay_frames(observed, simulated, views)
    rows = video[np.unique(np.linspace(0, len(video) - 1, min(frames, len(video))).round().astype(int))]
    return tile_views(rows[:, None], cols=1, pad=2)[0]


def body_collider_gap(recon: Reconstruction) -> float | None:
    """Smallest distance (m) from the first frame's body particles to the reconstructed
    collider's mesh (negative: inside it), or None without one."""
    if recon.collider_mesh is None:
        return None
    import trimesh

    return float(-np.max(trimesh.proximity.signed_distance(recon.collider_mesh, recon.points)))


def camera_warnings(offsets: ViewOffsets | None, recalibrated_views: bool = False) -> list[str]:
    """A warning per view the cameras' check flagged (none when they were recalibrated)."""
    if offsets is None or recalibrated_views:
        return []
    return [f"{line}: its camera is probably miscalibrated, and the fit trusts its shifted silhouettes (3 px in one "
            "of six views moved μ by 0.13 decades in docs/identify.md). Check its calibration, or rerun with "
            "--recalibrate-views, which moves its principal point by that offset" for line in offsets.describe()]


def identify_warnings(result, recon: Reconstruction, dx: float, offsets: ViewOffsets | None = None,
                      recalibrated_views: bool = False) -> list[str]:
    """What in the identification contradicts the data, with its likely cause and remedy.

    * A view's masks sit a pixel or more off the silhouette of the other views' visual hull
      (:func:`jaxmpm.reconstruct.calibration.view_offsets`): its camera is probably
      miscalibrated (said only when ``recalibrated_views`` did not correct it).
    * The fit found the body in contact from its first frame while the silhouettes show it
      falling freely for two or more frames: the reconstructed collider reaches too close
      to the body. A visual hull cannot carve what no silhouette edge touches — the top of
      a box seen from above keeps a "roof" where the views' cones meet — so the material
      lands on the roof and the fit explains the difference with a wrong material.
    * No view is level with the collider's top: :func:`roof_height` bounds its roof above
      half a cell (measured: lowest view 15° up, bound 0.8 dx, roof 1 dx, and the
      identification on the reconstructed box failed; docs/identify.md §4).
    """
    out = camera_warnings(offsets, recalibrated_views)
    if recon.collider_roof is not None and recon.collider_roof[0] > 0.5 * dx:
        h, theta = recon.collider_roof
        out.append(
            f"the lowest view is {theta:.0f}° above the reconstructed collider's top, which may therefore stand up to "
            f"{1e3 * h:.0f} mm ({h / dx:.1f} dx) above the true one (a visual hull cannot carve a flat top that no "
            "view sees edge-on). Add a view level with the collider's top"
        )
    fall = recon.free_fall
    contact_at_start = any("in contact from the start" in n for n in getattr(result, "notes", []))
    if contact_at_start and recon.collider is not None and fall is not None and fall.frames >= 2:
        gap = body_collider_gap(recon)
        where = f" (the body's particles are {1e3 * gap:.0f} mm = {gap / dx:.2f} dx from it)" if gap is not None else ""
        out.append(
            f"the silhouettes show the body falling freely for {fall.frames} frames, but in the simulation it touches "
            f"the reconstructed collider from the start{where}: the collider is probably too large on the side facing "
            "the body (a roof its views cannot carve), and the material parameters compensate for it. Add views "
            "near the horizon, or give the collider's geometry in the hint (a plane or a mesh)"
        )
    return out


def write_report(path: Path, result, recon: Reconstruction, iou: np.ndarray, times: np.ndarray, material: str,
                 warnings: list[str] | None = None, offsets: ViewOffsets | None = None,
                 recalibrated_views: bool = False) -> None:
    """``report.md``: parameters ± σ (and, with the fit's numerics check, the moves of its
    refits at dt/2 and with the other transfer), IoU over time per view, the cameras'
    consistency check, reconstruction quality."""
    lines = [f"# identify: {material}", ""]
    for w in warnings or []:
        lines += [f"> **Warning**: {w}.", ""]
    header = ("parameter", "estimate", "σ") + tuple(h for _, h in numerics_columns(result.numerics))
    lines += ["## Parameters", "", "| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    for name, value in result.values.items():
        cells = (name, format_value(value), format_value(result.std.get(name))) + numerics_cells(result.numerics, name)
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", f"{result.message}; {result.iterations} iterations, {result.seconds:.1f} s.", "",
              "## Silhouette IoU over time (observed vs simulated)", "",
              "![IoU per view over time](iou.png)", "",
              "![observed (red) and simulated (green) silhouettes, overlap yellow; a row per frame, a column per view]"
              "(overlay_frames.png)", "",
              "| t (s) | " + " | ".join(f"view {v}" for v in range(iou.shape[0])) + " |",
              "|---" * (iou.shape[0] + 1) + "|"]
    for t in range(iou.shape[1]):
        lines.append(f"| {times[t]:.4g} | " + " | ".join(f"{iou[v, t]:.3f}" for v in range(iou.shape[0])) + " |")
    if offsets is not None:
        fixed = offsets.flagged() if recalibrated_views else np.zeros(len(offsets.iou), bool)
        lines += ["", "## Cameras", "",
                  f"Each view's masks against the silhouette of the other views' visual hull (frames "
                  f"{', '.join(map(str, offsets.frames))}): the offset that overlaps them best, and the IoU before "
                  "and after it. A view is flagged at 1 px or more with an IoU gain of 0.01 or more.", "",
                  "| view | offset across, down (px) | IoU | IoU shifted | |", "|---|---|---|---|---|"]
        for v, ((du, dv), a, b, flag) in enumerate(zip(offsets.offsets, offsets.iou, offsets.iou_shifted,
                                                      offsets.flagged())):
            what = ("flagged; principal point moved by the offset" if fixed[v] else "flagged") if flag else ""
            lines.append(f"| {v} | {du:+.2f}, {dv:+.2f} | {a:.3f} | {b:.3f} | {what} |")
    lines += ["", "## Reconstruction", "",
              f"- body: {len(recon.points)} particles, visual-hull volume {recon.body_hull.volume:.4g} m³ "
              f"(a voxel kept when at least {recon.body_hull.views - recon.body_hull.tolerance} of the "
              f"{recon.body_hull.views} views see it)",
              "- first-frame IoU per view (observed vs re-rendered particles): "
              + ", ".join(f"{x:.3f}" for x in recon.body_iou)]
    ref = recon.refinement
    if ref is not None:
        lines.append(f"- first-frame refinement ({'masks and RGB' if ref.colors is not None else 'masks'}, "
                     f"{len(ref.loss)} steps): {ref.removed} of {len(ref.opacity)} hull particles removed; IoU per view "
                     f"before: " + ", ".join(f"{x:.3f}" for x in ref.iou_before))
    if recon.collider_mesh is not None:
        lines.append(f"- collider mesh: {len(recon.collider_mesh.faces)} faces, volume {recon.collider_mesh.volume:.4g} m³")
    if recon.surfels is not None:
        how = ("fitted to the collider masks and the plates' colours, as fitted" if recon.surfels.colors is not None
               else "fitted to the collider masks, put back on the hull")
        lines.append(f"- collider surfels ({how}): {len(recon.surfels.centers)} kept; IoU per view with the collider "
                     "masks: " + ", ".join(f"{x:.3f}" for x in recon.surfels.iou))
    lines.append(f"- the scene uses the reconstructed collider as: {recon.collider or 'none (no data/c_*.png)'}")
    if recon.collider_roof is not None:
        h, theta = recon.collider_roof
        lines.append(f"- the lowest view is {theta:.1f}° above the collider's top, so its top may stand up to "
                     f"{1e3 * h:.0f} mm above the true one (a visual hull cannot carve a flat top that no view sees "
                     "edge-on; a view level with the top removes this)")
    if recon.free_fall is not None:
        lines += free_fall_lines(recon.free_fall, recon.spec["gravity"])
    path.write_text("\n".join(lines) + "\n")


def free_fall_lines(fall: FreeFall, scene_gravity: list[float]) -> list[str]:
    """``report.md``'s lines on the free fall (:func:`jaxmpm.reconstruct.free_fall.free_fall`)
    of a scene whose gravity is ``scene_gravity`` (m/s²): its frames, how they were decided
    where the masks are too noisy for the shape test, the velocity, and the gravity measured
    and whether the scene uses it."""
    if fall.supported:
        lines = [f"- no free fall: the centres of the first {fall.supported} frames fit a straight line (RMS "
                 f"{1e3 * fall.residual:.2f} mm), not the parabola of the scene's gravity: the body is supported "
                 "from the start"]
    else:
        lines = [f"- free fall: {fall.frames} frames fit one parabola (RMS {1e3 * fall.residual:.2f} mm)"]
    if not fall.shape_tested:
        lines.append(f"- the masks' areas jump by {100 * fall.area_noise:.0f} % (σ) from frame to frame, too much to "
                     "tell contact by the silhouettes' size: the free fall is the frames whose centres follow the "
                     f"parabola of the scene's gravity {scene_gravity} m/s², and gravity is not measured")
    if fall.velocity is not None:
        lines.append(f"- initial velocity from the {'supported frames' if fall.supported else 'free fall'} (the fit's "
                     "starting guess): " + ", ".join(f"{v:.3f}" for v in fall.velocity) + " m/s")
    if fall.gravity is not None:
        used = fall.frames >= GRAVITY_FRAMES and list(scene_gravity) == [float(g) for g in fall.gravity]
        lines.append("- gravity from the free fall: " + ", ".join(f"{g:.2f}" for g in fall.gravity)
                     + f" m/s² (|g| = {np.linalg.norm(fall.gravity):.2f}); "
                     + ("used by the scene" if used else f"not used (the scene's: {scene_gravity})"))
    return lines


@dataclass
class IdentifyResult:
    """Outcome of :func:`identify`: the fit, the reconstruction, IoU ``(V, T)``, the files
    written, what contradicts the data (:func:`identify_warnings`) and the cameras'
    consistency check (:func:`jaxmpm.reconstruct.calibration.view_offsets`; None with fewer
    than 3 views)."""

    fit: object
    reconstruction: Reconstruction
    iou: np.ndarray
    files: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    view_offsets: ViewOffsets | None = None


def identify(
    folder: str | os.PathLike,
    material: str,
    out: str | os.PathLike,
    *,
    params: list[str] | None = None,
    hint=None,
    tolerance: int | None = None,
    collider: str = "mesh",
    max_steps: int | None = None,
    num_pixels: int = 256,
    surfel_steps: int = 80,
    refine: int = 0,
    rgb: float = 0.0,
    collider_rgb: float = 0.0,
    refine_velocity: bool | None = None,
    numerics: bool = False,
    recalibrate_views: bool = False,
    video: bool = True,
    stage: Callable[[str], None] | None = None,
    progress: Callable[[int, float], None] | None = None,
    warn: Callable[[str], None] | None = None,
) -> IdentifyResult:
    """Reconstruct the scene from a PAC-NeRF-layout folder and identify the material.

    Arguments:
        folder: the dataset (see docs/file_formats.md).
        material: material model name.
        out: output folder: ``scene.toml`` (+ ``body.npy``, ``collider.obj``,
            ``collider_disks.npz``), ``fit.json`` (as ``jaxmpm fit``), ``report.md`` with its
            pictures ``iou.png`` (IoU per view over time) and ``overlay_frames.png`` (observed
            and simulated silhouettes, a row per frame), ``overlay.mp4``.
        params: parameter names (default: the material's, plus ``velocity``).
        hint: ``scene_hint.toml`` path or dict (default ``folder/scene_hint.toml``).
        tolerance, collider, surfel_steps, refine, collider_rgb: see :func:`reconstruct`.
        max_steps, num_pixels, rgb, refine_velocity, numerics: of the fit (:func:`identify_material`; with
            ``refine`` and RGB the particles' fitted colours are the RGB term's).
        recalibrate_views: move the principal point of every view that the cameras' check
            (:func:`jaxmpm.reconstruct.calibration.view_offsets`, run before anything else on 3
            views or more) flags by its offset, before the reconstruction; otherwise a flagged
            view is only a warning.
        video: write the overlay video.
        stage: called with the name of each stage as it starts.
        progress: ``progress(step, loss)`` within the surfel fit and the material fit.
        warn: called with each of the cameras' warnings as soon as the check has run, before
            the long stages (they are in :attr:`IdentifyResult.warnings` too).

    Returns:
        An :class:`IdentifyResult`.
    """
    import imageio.v2 as imageio

    from ..constitutive import MATERIALS
    from ..plots import iou_curves
    from ..render import write_video
    from ..scene import load_scene

    say = stage or (lambda s: None)
    say("read")
    dataset = read_dataset(folder, hint)
    if material not in MATERIALS:
        raise ObservationError(f"unknown material {material!r}; expected one of {', '.join(sorted(MATERIALS))}")
    names = list(params) if params else list(MATERIALS[material].required()) + ["velocity"]
    _check_rgb_weight(rgb, dataset.observation.images)
    say("check cameras")
    domain = scene_skeleton(dataset, material)["domain"]
    dataset, offsets = check_cameras(dataset, domain["lo"], domain["hi"], recalibrate=recalibrate_views)
    for w in camera_warnings(offsets, recalibrate_views):
        (warn or (lambda _: None))(w)
    say("reconstruct")
    recon = reconstruct(dataset, material, tolerance=tolerance, collider=collider, surfel_steps=surfel_steps,
                        refine=refine, collider_rgb=collider_rgb, progress=progress)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    try:  # everything is written to a staging folder and moved into `out` at the end
        say("write scene")
        scene = load_scene(write_scene(recon, staging))
        say("fit")
        colors = "auto" if recon.refinement is None or recon.refinement.colors is None else recon.refinement.colors
        result = identify_material(scene, dataset.observation, names, max_steps=max_steps, num_pixels=num_pixels,
                                   rgb=rgb, colors=colors, refine_velocity=refine_velocity, numerics=numerics,
                                   progress=progress)
        (staging / "fit.json").write_text(json.dumps(result.to_json(), indent=2) + "\n")
        say("evaluate")
        evaluation_notes: list[str] = []
        sim = simulated_masks(scene, result.params, dataset.observation, result.substeps, notes=evaluation_notes)
        iou = silhouette_iou(sim, dataset.observation.masks)
        warnings = identify_warnings(result, recon, float(scene.model.grid.dx), offsets,
                                     recalibrate_views) + evaluation_notes
        times = np.asarray(dataset.observation.times)
        write_report(staging / "report.md", result, recon, iou, times, material, warnings, offsets, recalibrate_views)
        imageio.imwrite(staging / "overlay_frames.png", overlay_sheet(dataset.observation.masks, sim))
        iou_curves(staging / "iou.png", iou, times)
        if video:
            write_video(staging / "overlay.mp4", overlay_frames(dataset.observation.masks, sim),
                        fps=max(1, round(1.0 / dataset.frame_dt)))
        out.mkdir(exist_ok=True)
        files = {}
        for f in sorted(staging.iterdir()):
            os.replace(f, out / f.name)
            files[f.stem] = out / f.name
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return IdentifyResult(fit=result, reconstruction=recon, iou=iou, files=files, warnings=warnings,
                          view_offsets=offsets)

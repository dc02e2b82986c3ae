"""Differentiable rendering of particles: cameras, a voxel volume renderer, 2D Gaussian
surfels, image losses and video output (DESIGN §4; docs/rendering.md)."""

from .camera import (
    Camera as Camera,
    as_camera_batch as as_camera_batch,
    check_image_size as check_image_size,
    intrinsics_from_fov as intrinsics_from_fov,
    load_cameras_json as load_cameras_json,
    look_at as look_at,
    mean_colors as mean_colors,
    pacnerf_rig as pacnerf_rig,
    pixel_of as pixel_of,
    project_points as project_points,
    save_cameras_json as save_cameras_json,
    stack_cameras as stack_cameras,
    unstack_cameras as unstack_cameras,
)
from .losses import (
    all_pixels as all_pixels,
    check_observation_images as check_observation_images,
    gather_pixels as gather_pixels,
    masked_rgb_l2 as masked_rgb_l2,
    render_pixels as render_pixels,
    rgb_loss as rgb_loss,
    sample_pixels as sample_pixels,
    silhouette_l2 as silhouette_l2,
    silhouette_loss as silhouette_loss,
    soft_iou_loss as soft_iou_loss,
)
from .surfels import SurfelRenderer as SurfelRenderer
from .video import (
    RENDERERS as RENDERERS,
    make_renderer as make_renderer,
    render_views as render_views,
    tile_views as tile_views,
    to_uint8 as to_uint8,
    write_video as write_video,
)
from .volume import (
    AbstractRenderer as AbstractRenderer,
    Rendered as Rendered,
    VolumeRenderer as VolumeRenderer,
    estimate_spacing as estimate_spacing,
)

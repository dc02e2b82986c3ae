"""From views to a scene: visual hulls, body particles, colliders as meshes and fitted 2D
Gaussian surfels, and the ``identify`` pipeline (docs/identify.md)."""

from .calibration import ViewOffsets as ViewOffsets
from .calibration import check_cameras as check_cameras
from .calibration import recalibrated as recalibrated
from .calibration import view_offsets as view_offsets
from .collider import Surfels as Surfels
from .collider import chamfer_distance as chamfer_distance
from .collider import fit_surfels as fit_surfels
from .collider import hull_mesh as hull_mesh
from .collider import roof_height as roof_height
from .dataset import Dataset as Dataset
from .dataset import read_dataset as read_dataset
from .dataset import read_hint as read_hint
from .free_fall import AREA_NOISE_LIMIT as AREA_NOISE_LIMIT
from .free_fall import FreeFall as FreeFall
from .free_fall import free_fall as free_fall
from .hull import Hull as Hull
from .hull import hull_particles as hull_particles
from .hull import silhouette_iou as silhouette_iou
from .hull import visual_hull as visual_hull
from .pipeline import IdentifyResult as IdentifyResult
from .pipeline import Reconstruction as Reconstruction
from .pipeline import identify as identify
from .pipeline import identify_material as identify_material
from .pipeline import reconstruct as reconstruct
from .pipeline import reconstruct_body as reconstruct_body
from .pipeline import reconstruct_colliders as reconstruct_colliders
from .pipeline import scene_skeleton as scene_skeleton
from .pipeline import simulated_masks as simulated_masks
from .pipeline import write_scene as write_scene
from .refine import BodyRefinement as BodyRefinement
from .refine import refine_body as refine_body

"""jaxmpm: a differentiable Material Point Method in pure JAX for system identification.

The public API is re-exported here; private module names may change.
"""

from . import constitutive as constitutive
from . import extensions as extensions
from . import identify as identify
from . import parameters as parameters
from . import reconstruct as reconstruct
from . import render as render
from .cache import enable_compilation_cache as enable_compilation_cache
from .colliders import Box as Box
from .colliders import Collider as Collider
from .colliders import GaussianDisks as GaussianDisks
from .colliders import MeshCollider as MeshCollider
from .colliders import Plane as Plane
from .colliders import asset_path as asset_path
from .colliders import project_velocity as project_velocity
from .constitutive import MATERIALS as MATERIALS
from .constitutive import Elastic as Elastic
from .constitutive import Material as Material
from .constitutive import Newtonian as Newtonian
from .constitutive import Plasticine as Plasticine
from .constitutive import Sand as Sand
from .constitutive import Viscoplastic as Viscoplastic
from .constitutive import polar_rotation as polar_rotation
from .constitutive import svd as svd
from .cpic import CollisionField as CollisionField
from .cpic import build_collision_field as build_collision_field
from .datasets import load_pacnerf as load_pacnerf
from .datasets import save_pacnerf as save_pacnerf
from .discover import discover as discover
from .errors import JaxmpmError as JaxmpmError
from .errors import JaxmpmWarning as JaxmpmWarning
from .errors import ObservationError as ObservationError
from .errors import SceneError as SceneError
from .errors import SimulationError as SimulationError
from .fit import FitConfig as FitConfig
from .fit import FitResult as FitResult
from .fit import fit as fit
from .fit import fit_scene as fit_scene
from .identify import build_objective as build_objective
from .model import Body as Body
from .model import Collision as Collision
from .model import Model as Model
from .model import contact_notes as contact_notes
from .model import initial_state as initial_state
from .parameters import Parameter as Parameter
from .observe import Observation as Observation
from .observe import load_observation as load_observation
from .observe import save_observation as save_observation
from .reconstruct import identify as identify_dataset
from .reconstruct import read_dataset as read_dataset
from .reconstruct import reconstruct as reconstruct_scene
from .reconstruct import visual_hull as visual_hull
from .scene import Scene as Scene
from .scene import load_scene as load_scene
from .state import Grid as Grid
from .state import State as State
from .state import make_state as make_state
from .step import Trajectory as Trajectory
from .step import run_frames as run_frames
from .step import simulate as simulate
from .step import simulate_healthy as simulate_healthy
from .step import stable_substeps as stable_substeps
from .step import step as step
from .sweep import sweep as sweep

__version__ = "0.1.0"

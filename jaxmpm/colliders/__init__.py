"""Rigid colliders: the abstract base and its motion (``base``), one module per shape
(``plane``, ``box``, ``mesh``, ``disks``) and the reading of collider specs and files
(``spec``, also used by :mod:`jaxmpm.scene` for bodies).
"""

from .base import CONTACTS as CONTACTS
from .base import Collider as Collider
from .base import RigidCollider as RigidCollider
from .base import StaticArray as StaticArray
from .base import cross_omega as cross_omega
from .base import project_velocity as project_velocity
from .base import rigid_transform as rigid_transform
from .base import rotation_matrix as rotation_matrix
from .base import row_dot as row_dot
from .base import row_matvec as row_matvec
from .base import rows_times as rows_times
from .base import vector as vector
from .box import Box as Box
from .disks import GaussianDisks as GaussianDisks
from .disks import orient_normals as orient_normals
from .mesh import MeshCollider as MeshCollider
from .mesh import closest_on_simplices as closest_on_simplices
from .plane import Plane as Plane
from .spec import COLLIDER_TYPES as COLLIDER_TYPES
from .spec import asset_path as asset_path
from .spec import box_from_spec as box_from_spec
from .spec import disks_from_spec as disks_from_spec
from .spec import load_disks as load_disks
from .spec import load_mesh as load_mesh
from .spec import load_polyline_npz as load_polyline_npz
from .spec import mesh_from_spec as mesh_from_spec
from .spec import place as place
from .spec import placement as placement
from .spec import plane_from_spec as plane_from_spec
from .spec import resolve_path as resolve_path

"""Constitutive models: one abstract :class:`Material` and its final subclasses (PAC-NeRF's five materials and fixed-corotated elasticity)."""

from .base import Material as Material
from .base import lame_from_young as lame_from_young
from .models import MATERIALS as MATERIALS
from .models import Corotated as Corotated
from .models import Elastic as Elastic
from .models import Newtonian as Newtonian
from .models import Plasticine as Plasticine
from .models import Sand as Sand
from .models import Viscoplastic as Viscoplastic
from .svd import polar_rotation as polar_rotation
from .svd import svd as svd

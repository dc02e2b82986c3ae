"""The identification core: parameters, residuals, solvers and uncertainty.

:func:`jaxmpm.fit` (staging, dt halving, the result) and :func:`jaxmpm.discover` (model
discrepancy) are built on these parts:

* :mod:`~jaxmpm.identify.parameters`: names -> paths in the parameter pytree, fitting spaces
  read from each parameter's declaration (:class:`jaxmpm.parameters.Parameter`);
* :mod:`~jaxmpm.identify.residuals`: residual vectors of tracks, silhouettes, masked RGB and
  probes (:func:`build_objective`) and the probe registry;
* :mod:`~jaxmpm.identify.solvers`: Levenberg–Marquardt (optimistix's algorithm on a fused
  residual-and-Jacobian function), its bounded variant,
  BFGS and Adam;
* :mod:`~jaxmpm.identify.uncertainty`: the Gauss–Newton covariance.
"""

from .parameters import ADAM_LEARNING_RATES as ADAM_LEARNING_RATES
from .parameters import LOG10_PARAMS as LOG10_PARAMS
from .parameters import apply_unconstrained as apply_unconstrained
from .parameters import declaration as declaration
from .parameters import default_names as default_names
from .parameters import from_unconstrained as from_unconstrained
from .parameters import get_param as get_param
from .parameters import resolve_name as resolve_name
from .parameters import set_param as set_param
from .parameters import to_unconstrained as to_unconstrained
from .residuals import Objective as Objective
from .residuals import back as back
from .residuals import build_objective as build_objective
from .residuals import centroid as centroid
from .residuals import depth_gauge as depth_gauge
from .residuals import front as front
from .residuals import gauge as gauge
from .residuals import probe_function as probe_function
from .residuals import probe_names as probe_names
from .residuals import probe_series as probe_series
from .residuals import register_probe as register_probe
from .residuals import top as top
from .solvers import SolverOutcome as SolverOutcome
from .solvers import levenberg_marquardt as levenberg_marquardt
from .uncertainty import gauss_newton_covariance as gauss_newton_covariance
from .uncertainty import resolved_std as resolved_std

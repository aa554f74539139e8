"""The inference pieces behind ``fit``, for a new solver or sampler and for tests.

``Geometry`` is the seam to the sample's shape (``LayeredBlock`` today, ``geometry_of``).
``Objective`` is the fit's Gaussian likelihood (residual rows, chi-square,
log-likelihood on the host and as a JAX function), shared by the solver and the sampler.
``QUANTITIES`` declares every fitted quantity once (``Quantity``: scene part and key,
unit, default, bounds, step, where the model takes it).
``free_parameters`` resolves a scene's ``[fit]`` into ``FreeParameter`` values and
``assembler`` maps their values to ``ModelParams``; ``Predictor`` evaluates the model
(T rows for free values), compiled once as one program per group of profiles and kept
between fits (``forget_compiled`` drops this process's copies, ``cache_dir`` is the
on-disk cache); ``levenberg_marquardt`` is the
default solver of residual rows; ``outer_edges``, ``one_edge``, ``refraction_edges``, ``segment`` and
``attenuation_from_plateau`` read starts off the data; ``assess`` and ``runs_z`` are the
quality gate; ``covariance`` and ``errors_and_correlation`` the uncertainty from the
Jacobian; ``diagnostics`` the sampler's effective sample sizes and R-hat; ``optimal_plan`` the
experiment design's exposure split for given information matrices.
"""

from ._cache import cache_dir as cache_dir
from ._design import optimal_plan as optimal_plan
from ._geometry import Geometry as Geometry
from ._geometry import LayeredBlock as LayeredBlock
from ._geometry import geometry_of as geometry_of
from ._least_squares import Solution as Solution
from ._objective import Objective as Objective
from ._least_squares import levenberg_marquardt as levenberg_marquardt
from ._parameters import Assembler as Assembler
from ._parameters import FreeParameter as FreeParameter
from ._parameters import assembler as assembler
from ._parameters import free_parameters as free_parameters
from ._predict import Predictor as Predictor
from ._predict import forget_compiled as forget_compiled
from ._quality import Quality as Quality
from ._quality import Region as Region
from ._quality import assess as assess
from ._quality import runs_z as runs_z
from ..scene._registry import QUANTITIES as QUANTITIES
from ..scene._registry import Quantity as Quantity
from ._sample import blackjax_module as blackjax_module
from ._sample import diagnostics as diagnostics
from ._starts import attenuation_from_plateau as attenuation_from_plateau
from ._starts import balanced_edges as balanced_edges
from ._starts import estimate as estimate_starts
from ._starts import one_edge as one_edge
from ._starts import outer_edges as outer_edges
from ._starts import refraction_edges as refraction_edges
from ._starts import segment as segment
from ._uncertainty import covariance as covariance
from ._uncertainty import errors_and_correlation as errors_and_correlation

"""The forward model and its parts: ``build_model`` plans a scene into a ``ForwardModel``
of ``ModelParams``; the aperture kernels (``APERTURES``), the angular mass and Fresnel
transfer of an interface, where the rays leaving a face land (``landing_range``, the
sub-windows ``landing_regions``), the Fresnel nodes, the depth pieces of a layer and the
wavelength quadrature of a spectrum. The shared parts sit here; each geometry has a
folder of its own (``block/``, the layered block)."""

from ._aperture import APERTURES as APERTURES
from ._kernel import AngularMass as AngularMass
from ._kernel import fresnel_transfer as fresnel_transfer
from ._kernel import landing_range as landing_range
from ._kernel import landing_regions as landing_regions
from .block._model import DEPTH_PIECES as DEPTH_PIECES
from .block._model import ForwardModel as ForwardModel
from .block._model import ModelParams as ModelParams
from .block._plan import build_model as build_model
from .block._plan import fresnel_nodes as fresnel_nodes
from .block._plan import initial_params as initial_params
from ..scene._spectrum import wavelength_quadrature as wavelength_quadrature

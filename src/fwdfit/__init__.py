"""fwdfit: differentiable forward-model fitting of refraction at interfaces in neutron radiographs.

The flow: scene file -> ``load_scene`` (or a ``Scene`` built in Python; ``dump_scene``
writes one) -> ``build_model`` + ``initial_params`` ->
``ForwardModel(params)`` gives (T, T_att) per profile -> ``fit`` -> result.
"""

from ._cache import enable_compilation_cache as enable_compilation_cache
from ._errors import FwdfitError as FwdfitError
from ._errors import ModelWarning as ModelWarning
from ._fit import FitResult as FitResult
from ._fit import FittedProfile as FittedProfile
from ._fit import Fitter as Fitter
from ._fit import fit as fit
from ._fit_output import write_fit as write_fit
from ._image_fit import ImageFit as ImageFit
from ._image_fit import fit_image as fit_image
from ._image_output import write_image_fit as write_image_fit
from ._materials import MaterialConstants as MaterialConstants
from ._materials import constants_from_formula as constants_from_formula
from ._materials import constants_from_ncrystal as constants_from_ncrystal
from ._model import ForwardModel as ForwardModel
from ._model import ModelParams as ModelParams
from ._paganin import paganin_filter_1d as paganin_filter_1d
from ._paganin import paganin_filter_2d as paganin_filter_2d
from ._paganin import paganin_tau_um2 as paganin_tau_um2
from ._paganin import paganin_tau_um2_spectrum as paganin_tau_um2_spectrum
from ._paganin import paganin_thickness_um as paganin_thickness_um
from ._plan import build_model as build_model
from ._plan import initial_params as initial_params
from ._radiograph import profile_from_stacks as profile_from_stacks
from ._reference import ReferenceLayer as ReferenceLayer
from ._reference import trace_reference as trace_reference
from ._reference import trace_reference_rows as trace_reference_rows
from ._sample import Posterior as Posterior
from ._sample import sample as sample
from ._scene import FitSpec as FitSpec
from ._scene import Instrument as Instrument
from ._scene import Layer as Layer
from ._scene import Profile as Profile
from ._scene import Sample as Sample
from ._scene import Scene as Scene
from ._scene import load_scene as load_scene
from ._scene import pixel_grid as pixel_grid
from ._scene_toml import dump_scene as dump_scene
from ._scene_toml import save_scene as save_scene
from ._spectrum import BandSpectrum as BandSpectrum
from ._spectrum import GaussianLine as GaussianLine
from ._spectrum import TabulatedSpectrum as TabulatedSpectrum
from ._simulate import SimulatedProfile as SimulatedProfile
from ._simulate import simulate as simulate

__version__ = "0.1.0"

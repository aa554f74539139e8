"""Scenes as values and files: the classes (constructible in Python), ``load_scene`` (the
reader, which checks the validity domain ``DOMAIN``), ``dump_scene``/``save_scene`` (the
one writer) and the CSV tables profiles and spectra are read from and written to."""

from ._limits import DOMAIN as DOMAIN
from ._limits import MAX_PIXELS as MAX_PIXELS
from ._limits import MAX_TILT_DEG as MAX_TILT_DEG
from ._materials import MaterialConstants as MaterialConstants
from ._scene import FitSpec as FitSpec
from ._scene import ImageLayout as ImageLayout
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
from ..io._tables import read_columns as read_columns
from ..io._tables import write_columns as write_columns

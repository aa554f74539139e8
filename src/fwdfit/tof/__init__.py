"""Time of flight: stacks of wavelength bins to one profile per bin (``tof_profiles``)
and the skeleton scene for them (``skeleton_toml``); the readers are in ``io``."""

from ._tof import TofProfiles as TofProfiles
from ._tof import tof_profiles as tof_profiles
from ._tof import wavelength_A as wavelength_A
from ._tof_scene import bin_names as bin_names
from ._tof_scene import skeleton_toml as skeleton_toml

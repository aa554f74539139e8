"""Paganin's single-material phase retrieval, and applied to a scene's measured profiles
(``paganin_profiles``: the material's constants from the scene's layer)."""

from ._paganin import paganin_filter_1d as paganin_filter_1d
from ._paganin import paganin_filter_2d as paganin_filter_2d
from ._paganin import paganin_tau_um2 as paganin_tau_um2
from ._paganin import paganin_tau_um2_spectrum as paganin_tau_um2_spectrum
from ._paganin import paganin_thickness_um as paganin_thickness_um
from ._paganin_scene import PaganinProfile as PaganinProfile
from ._paganin_scene import paganin_layer as paganin_layer
from ._paganin_scene import paganin_profiles as paganin_profiles
from ._paganin_scene import profile_tau_um2 as profile_tau_um2

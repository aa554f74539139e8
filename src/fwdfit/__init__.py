"""fwdfit: differentiable forward-model fitting of refraction at interfaces in neutron radiographs.

The flow: scene file -> ``load_scene`` (or a ``Scene`` built in Python; ``dump_scene``
writes one) -> ``build_model`` + ``initial_params`` ->
``ForwardModel(params)`` gives (T, T_att) per profile -> ``fit`` -> result.
"""

from importlib import import_module

from ._version import __version__ as __version__

# Each public name and its module, imported on first use (PEP 562): ``import fwdfit``
# and the command line's start (its Ctrl-C handler, ``--version``) do not import JAX.
_PUBLIC = {
    "enable_compilation_cache": "_cache",
    "FwdfitError": "_errors",
    "ModelWarning": "_errors",
    "FitResult": "_fit",
    "FittedProfile": "_fit",
    "Fitter": "_fit",
    "fit": "_fit",
    "write_fit": "_fit_output",
    "ImageFit": "_image_fit",
    "fit_image": "_image_fit",
    "write_image_fit": "_image_output",
    "MaterialConstants": "_materials",
    "constants_from_formula": "_materials",
    "constants_from_ncrystal": "_materials",
    "ForwardModel": "_model",
    "ModelParams": "_model",
    "paganin_filter_1d": "_paganin",
    "paganin_filter_2d": "_paganin",
    "paganin_tau_um2": "_paganin",
    "paganin_tau_um2_spectrum": "_paganin",
    "paganin_thickness_um": "_paganin",
    "build_model": "_plan",
    "initial_params": "_plan",
    "profile_from_stacks": "_radiograph",
    "ReferenceLayer": "_reference",
    "trace_reference": "_reference",
    "trace_reference_rows": "_reference",
    "Posterior": "_sample",
    "sample": "_sample",
    "FitSpec": "_scene",
    "Instrument": "_scene",
    "Layer": "_scene",
    "Profile": "_scene",
    "Sample": "_scene",
    "Scene": "_scene",
    "load_scene": "_scene",
    "pixel_grid": "_scene",
    "dump_scene": "_scene_toml",
    "save_scene": "_scene_toml",
    "BandSpectrum": "_spectrum",
    "GaussianLine": "_spectrum",
    "TabulatedSpectrum": "_spectrum",
    "SimulatedProfile": "_simulate",
    "simulate": "_simulate",
}
__all__ = ["__version__", *_PUBLIC]


def __getattr__(name: str):
    if name not in _PUBLIC:
        raise AttributeError(f"module 'fwdfit' has no attribute {name!r}")
    value = getattr(import_module(f".{_PUBLIC[name]}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)

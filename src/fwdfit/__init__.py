"""fwdfit: differentiable forward-model fitting of refraction at interfaces in neutron radiographs.

The flow: scene file -> ``load_scene`` (or a ``Scene`` built in Python; ``dump_scene``
writes one) -> ``build_model`` + ``initial_params`` ->
``ForwardModel(params)`` gives (T, T_att) per profile -> ``fit`` -> result.

The layout, bottom to top: a module imports its own folder or a lower rank, never a
higher one nor a sibling of its rank, and no import loops (tests/test_layout.py):

0 the root: _errors, _version, _interrupt, _progress (the standard library only)
1 io/ (tables, time-of-flight readers); 1 reference/ (the exact tracer)
2 scene/ (values, the TOML reader and writer, registry, limits, materials, spectra)
3 model/ (the shared kernel and aperture); 3 paganin/ (phase retrieval)
4 model/block/ (the layered block's plan, model and thin layers; one folder per geometry);
  4 model/cylinder/ (concentric shells: rods and tubes)
5 inference/ (free parameters, starts, search, solver, objective, predictor and cache,
  uncertainty, quality gate, fitter, sampler, simulate)
6 outputs/ (a fit's files)
7 images/ (TIFF stacks to profiles, image fits and series)
8 tof/ (time-of-flight profiles)
9 cli/ (the ``fwdfit`` command)
"""

from importlib import import_module

from ._version import __version__ as __version__

# Each public name and its module, imported on first use (PEP 562): ``import fwdfit``
# and the command line's start (its Ctrl-C handler, ``--version``) do not import JAX.
_PUBLIC = {
    "enable_compilation_cache": "inference._cache",
    "FwdfitError": "_errors",
    "ModelWarning": "_errors",
    "FitResult": "inference._fit",
    "FittedProfile": "inference._fit",
    "Fitter": "inference._fit",
    "fit": "inference._fit",
    "design": "inference._design",
    "Design": "inference._design",
    "write_fit": "outputs._fit_output",
    "ImageFit": "images._image_fit",
    "fit_image": "images._image_fit",
    "write_image_fit": "images._image_output",
    "MaterialConstants": "scene._materials",
    "constants_from_formula": "scene._materials",
    "constants_from_ncrystal": "scene._materials",
    "ForwardModel": "model.block._model",
    "ModelParams": "model.block._model",
    "paganin_filter_1d": "paganin._paganin",
    "paganin_filter_2d": "paganin._paganin",
    "paganin_tau_um2": "paganin._paganin",
    "paganin_tau_um2_spectrum": "paganin._paganin",
    "paganin_thickness_um": "paganin._paganin",
    "build_model": "model.block._plan",
    "initial_params": "model.block._plan",
    "profile_from_stacks": "images._radiograph",
    "ReferenceLayer": "reference._reference",
    "trace_reference": "reference._reference",
    "trace_reference_rows": "reference._reference",
    "trace_cylinder_reference": "reference._cylinder_reference",
    "Posterior": "inference._sample",
    "sample": "inference._sample",
    "DesignSpec": "scene._design_spec",
    "FitSpec": "scene._scene",
    "Instrument": "scene._scene",
    "Layer": "scene._scene",
    "Profile": "scene._scene",
    "Sample": "scene._scene",
    "Scene": "scene._scene",
    "load_scene": "scene._scene",
    "pixel_grid": "scene._scene",
    "dump_scene": "scene._scene_toml",
    "save_scene": "scene._scene_toml",
    "BandSpectrum": "scene._spectrum",
    "GaussianLine": "scene._spectrum",
    "TabulatedSpectrum": "scene._spectrum",
    "SimulatedProfile": "inference._simulate",
    "simulate": "inference._simulate",
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

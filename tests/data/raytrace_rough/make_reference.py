"""Regenerate the rough-face and graded-layer reference profiles of this folder with the exact ray tracer.

Cases (scenes built here and written as ``<case>/scene.toml`` with ``fwdfit.save_scene``):

- ``rough0.5_icon``, ``rough2_icon``: a 1000 µm Al block whose two faces have RMS normal slopes of
  0.5 and 2 mrad, ICON (circular aperture), 4.6 Å line, tilt 0.24°, at 1.1 and 10 mm, pixels
  around the left edge only;
- ``rough2_boa``: the same block with 2 mrad, BOA (square aperture, white beam), tilt 0;
- ``graded``: a 150 µm coating graded from SLD 3.0 to 1.6 (1e-6 Å^-2) and mu 400 to 120 /m
  (left to right) on 850 µm of Al, ICON 4.6 Å, tilt 0.24°, traced as 50 uniform sublayers.

Each rough profile is traced twice with the same seed (the same rays): with Fresnel partial
reflection (columns T, T_err, T_att, T_att_err) and without it (T_sharp_fresnel_off: the rough
block without Fresnel reflection). The graded profiles are traced once, without Fresnel
reflection. Gaussian lines are tabulated on 801 points over their support. Writes
``<case>/<profile>.csv`` and ``<case>/case.json`` (ray counts, seed, timings).

    cd tests/data/raytrace_rough && PYTHONPATH=../../../src python3 make_reference.py [case ...]
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

import fwdfit
from fwdfit.reference import ReferenceLayer, trace_reference
from fwdfit.scene import GaussianLine

HERE = Path(__file__).parent
FRESNEL = HERE.parent / "raytrace_fresnel"
RAYS_PER_UM = 25_000  # rays per µm of the tracer's aim window
N_BATCHES = 10
SEED = 160
GRADED_SUBLAYERS = 50


def _scene(name: str):
    """The case's scene (instrument and spectra from the Fresnel references' ICON or BOA scene)."""
    boa = name.endswith("boa")
    base = fwdfit.load_scene(FRESNEL / ("al_boa_tilt0" if boa else "al_icon_tilt0.24") / "scene.toml")
    spectrum = "white" if boa else "l4.6A"
    instrument = dataclasses.replace(base.instruments[""], fresnel=name != "graded")
    al = base.sample.layers[0]
    if name == "graded":
        coating = fwdfit.Layer("coating", 150.0, 3.0, 400.0, sld_end_e6_per_A2=1.6, mu_end_per_m=120.0)
        layers, x = (coating, dataclasses.replace(al, thickness_um=850.0)), (-580.0, -280.0)
    else:
        rough = float(name.split("_")[0].removeprefix("rough"))
        layers, x = (dataclasses.replace(al, roughness_mrad=rough),), (-620.0, -380.0)
    sample = dataclasses.replace(base.sample, layers=layers, tilt_deg=0.0 if boa else 0.24,
                                 left_roughness_mrad=layers[0].roughness_mrad)
    pixel = instrument.pixel_um
    grid = np.arange(x[0], x[1], pixel) + 0.5 * pixel
    profiles = tuple(fwdfit.Profile(f"d{d:04.1f}mm", d, spectrum, "", grid) for d in (1.1, 10.0))
    return dataclasses.replace(base, sample=sample, instruments={"": instrument},
                               spectra={spectrum: base.spectra[spectrum]}, profiles=profiles, path=None)


def _spectrum_table(spectrum):
    if isinstance(spectrum, GaussianLine):
        lam = np.linspace(*spectrum.support_A, 801)
        return lam, spectrum.density(lam)
    return np.asarray(spectrum.lambda_A), np.asarray(spectrum.weight)


def make(name: str) -> None:
    scene = _scene(name)
    case_dir = HERE / name
    case_dir.mkdir(exist_ok=True)
    fwdfit.save_scene(scene, case_dir / "scene.toml")
    layers = [ReferenceLayer(l.thickness_um, l.sld_e6_per_A2, l.mu_per_m, l.mu_per_m_per_A,
                             roughness_mrad=l.roughness_mrad,
                             sld_end_e6_per_A2=None if np.isnan(l.sld_end_e6_per_A2) else l.sld_end_e6_per_A2,
                             mu_end_per_m=None if np.isnan(l.mu_end_per_m) else l.mu_end_per_m)
              for l in scene.sample.layers]
    log = {"tracer": "fwdfit.reference.trace_reference", "n_batches": N_BATCHES,
           "graded_sublayers": GRADED_SUBLAYERS, "profiles": []}
    for i, profile in enumerate(scene.profiles):
        instrument = scene.instruments[profile.instrument]
        lam, weight = _spectrum_table(scene.spectra[profile.spectrum])
        edges = np.append(profile.x_um - 0.5 * instrument.pixel_um, profile.x_um[-1] + 0.5 * instrument.pixel_um)
        aim_um = edges[-1] - edges[0] + 2 * (0.02 * (1e3 * profile.distance_mm + 1e3) + 50.0)
        n_rays = int(RAYS_PER_UM * aim_um)
        kwargs = dict(depth_mm=scene.sample.depth_mm, tilt_deg=scene.sample.tilt_deg,
                      centre_um=scene.sample.centre_um, aperture=instrument.aperture,
                      aperture_mm=instrument.aperture_mm, aperture_distance_m=instrument.aperture_distance_m,
                      distance_mm=profile.distance_mm, spectrum_lambda_A=lam, spectrum_weight=weight,
                      pixel_edges_um=edges, psf_fwhm_um=instrument.psf_fwhm_um, n_rays=n_rays,
                      seed=SEED + i, n_batches=N_BATCHES, left_roughness_mrad=scene.sample.left_roughness_mrad,
                      graded_sublayers=GRADED_SUBLAYERS)
        start = time.perf_counter()
        ref = trace_reference(layers, fresnel=instrument.fresnel, **kwargs)
        columns = [profile.x_um, ref.T, ref.T_err, ref.T_att, ref.T_att_err]
        header = "x_um,T,T_err,T_att,T_att_err"
        if instrument.fresnel:
            columns.append(trace_reference(layers, fresnel=False, **kwargs).T)
            header += ",T_fresnel_off"
        elapsed = time.perf_counter() - start
        np.savetxt(case_dir / f"{profile.name}.csv", np.column_stack(columns), delimiter=",", fmt="%.8g",
                   header=header, comments="")
        log["profiles"].append({"name": profile.name, "n_rays": n_rays, "seed": SEED + i, "elapsed_s": elapsed,
                                "n_dropped": ref.n_dropped, "rms_T_err": float(np.sqrt(np.mean(ref.T_err ** 2))),
                                "max_T_err": float(np.max(ref.T_err))})
        print(name, profile.name, f"{elapsed:.0f} s", flush=True)
    (case_dir / "case.json").write_text(json.dumps(log, indent=1) + "\n")


if __name__ == "__main__":
    for case in sys.argv[1:] or ["rough0.5_icon", "rough2_icon", "rough2_boa", "graded"]:
        make(case)

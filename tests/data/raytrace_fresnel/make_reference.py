"""Regenerate the Fresnel reference profiles of this folder with the project's exact ray tracer.

For every ``<case>/scene.toml`` here and each of its profiles, ``fwdfit.reference.trace_reference``
runs twice with the same seed: with Fresnel partial reflection (columns T, T_err, T_att,
T_att_err) and without it (T_sharp). The rays are the same in both runs (correlated sampling),
so T - T_sharp has far less noise than T. Gaussian lines are tabulated on 801 points over the
line's support (``support_A``), tables are used as they are. Writes ``<case>/<profile>.csv``
and ``<case>/case.json`` (ray counts, seed, timings).

    cd tests/data/raytrace_fresnel && PYTHONPATH=../../../src python3 make_reference.py [case ...]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

import fwdfit
from fwdfit.reference import ReferenceLayer, trace_reference
from fwdfit.scene import GaussianLine

N_RAYS = 40_000_000  # profiles up to 5 mm from the sample
N_RAYS_FAR = 60_000_000  # further away (their rays spread over a wider aim window)
N_BATCHES = 10
SEED = 16


def _spectrum_table(spectrum):
    if isinstance(spectrum, GaussianLine):
        lam = np.linspace(*spectrum.support_A, 801)
        return lam, spectrum.density(lam)
    return np.asarray(spectrum.lambda_A), np.asarray(spectrum.weight)


def make(case_dir: Path) -> None:
    scene = fwdfit.load_scene(case_dir / "scene.toml")
    layers = [ReferenceLayer(l.thickness_um, l.sld_e6_per_A2, l.mu_per_m, l.mu_per_m_per_A)
              for l in scene.sample.layers]
    log = {"tracer": "fwdfit.reference.trace_reference", "n_batches": N_BATCHES, "profiles": []}
    for i, profile in enumerate(scene.profiles):
        instrument = scene.instruments[profile.instrument]
        n_rays = N_RAYS if profile.distance_mm <= 5.0 else N_RAYS_FAR
        lam, weight = _spectrum_table(scene.spectra[profile.spectrum])
        edges = np.append(profile.x_um - 0.5 * instrument.pixel_um, profile.x_um[-1] + 0.5 * instrument.pixel_um)
        kwargs = dict(depth_mm=scene.sample.depth_mm, tilt_deg=scene.sample.tilt_deg,
                      centre_um=scene.sample.centre_um, aperture=instrument.aperture,
                      aperture_mm=instrument.aperture_mm, aperture_distance_m=instrument.aperture_distance_m,
                      distance_mm=profile.distance_mm, spectrum_lambda_A=lam, spectrum_weight=weight,
                      pixel_edges_um=edges, psf_fwhm_um=instrument.psf_fwhm_um, n_rays=n_rays,
                      seed=SEED + i, n_batches=N_BATCHES)
        start = time.perf_counter()
        fresnel = trace_reference(layers, fresnel=True, **kwargs)
        sharp = trace_reference(layers, fresnel=False, **kwargs)
        elapsed = time.perf_counter() - start
        table = np.column_stack([profile.x_um, fresnel.T, fresnel.T_err, fresnel.T_att, fresnel.T_att_err,
                                 sharp.T])
        np.savetxt(case_dir / f"{profile.name}.csv", table, delimiter=",", fmt="%.8g",
                   header="x_um,T,T_err,T_att,T_att_err,T_sharp", comments="")
        log["profiles"].append({"name": profile.name, "n_rays": n_rays, "seed": SEED + i, "elapsed_s": elapsed,
                                "n_dropped": fresnel.n_dropped,
                                "rms_T_err": float(np.sqrt(np.mean(fresnel.T_err ** 2))),
                                "max_T_err": float(np.max(fresnel.T_err))})
        print(case_dir.name, profile.name, f"{elapsed:.0f} s", flush=True)
    (case_dir / "case.json").write_text(json.dumps(log, indent=1) + "\n")


if __name__ == "__main__":
    here = Path(__file__).parent
    names = sys.argv[1:] or sorted(p.parent.name for p in here.glob("*/scene.toml"))
    for name in names:
        make(here / name)

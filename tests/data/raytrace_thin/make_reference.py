"""Make the thin-layer reference profiles of this folder with the project's exact ray tracer.

Cases (each ``<case>/scene.toml``, written here with ``fwdfit.scene.save_scene``, and one CSV per
profile): an oxide skin (SLD 4.5e-6 Å^-2, mu 100 /m + 0.3 /m/Å) of 2 µm or 1.2 µm on both sides
of 1 mm of Al (profiles over the left edge), and a 4 µm Ti layer (SLD -1.95, mu 60 /m, i.e.
0.6 /cm) between two 500 µm Al blocks (profiles over the Ti), at tilts 0 and 0.24°; each with a
BOA white-beam profile at 1.1 and 10 mm (square 40 mm aperture at 7.5 m) and an ICON 4 Å line
(FWHM 15 %, circular 40 mm at 5.5 m) at 1.1 mm; no detector blur. ``trace_reference`` runs with
N_RAYS rays in N_BATCHES batches (columns x_um, T, T_err, T_att, T_att_err). Gaussian lines are
tabulated on 801 points over their support. A case named ``<case>_fresnel`` is the same with
Fresnel partial reflection on (``fresnel = true`` in both instruments, ``trace_reference(...,
fresnel=True)``).

    cd tests/data/raytrace_thin && PYTHONPATH=../../../src python3 make_reference.py [case ...]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

import fwdfit
from fwdfit.reference import ReferenceLayer, trace_reference
from fwdfit.scene import GaussianLine, TabulatedSpectrum, read_columns

N_RAYS = {1.1: 20_000_000, 10.0: 40_000_000}
N_BATCHES = 8
SEED = 160
HERE = Path(__file__).parent
AL = dict(sld_e6_per_A2=2.078, mu_per_m=1.39, mu_per_m_per_A=0.1)
SKIN = dict(sld_e6_per_A2=4.5, mu_per_m=100.0, mu_per_m_per_A=0.3)
TI = dict(sld_e6_per_A2=-1.95, mu_per_m=60.0, mu_per_m_per_A=0.0)


def _layers(sample: str):
    if sample.startswith("skin"):
        t = float(sample[4:])
        return (fwdfit.Layer("skin_l", t, **SKIN), fwdfit.Layer("Al", 1000.0, **AL),
                fwdfit.Layer("skin_r", t, **SKIN)), -(500.0 + t)  # the left outer face
    return (fwdfit.Layer("Al_l", 500.0, **AL), fwdfit.Layer("Ti", 4.0, **TI), fwdfit.Layer("Al_r", 500.0, **AL)), 0.0


def scene_of(sample: str, tilt_deg: float, fresnel: bool = False) -> fwdfit.Scene:
    """The case's scene: BOA profiles at 1.1 and 10 mm and an ICON line at 1.1 mm."""
    layers, edge = _layers(sample)
    table = read_columns(HERE / "spectrum_boa.csv", ("lambda_A", "weight"))
    grid = lambda half: fwdfit.pixel_grid(edge - half, edge + half, 2.4)
    return fwdfit.Scene(
        sample=fwdfit.Sample(depth_mm=2.0, tilt_deg=tilt_deg, centre_um=0.0, layers=layers),
        instruments={"boa": fwdfit.Instrument("square", 40.0, 7.5, 2.4, fresnel=fresnel),
                     "icon": fwdfit.Instrument("circular", 40.0, 5.5, 2.4, fresnel=fresnel)},
        spectra={"white": TabulatedSpectrum(table["lambda_A"], table["weight"], HERE / "spectrum_boa.csv"),
                 "l40": GaussianLine(4.0, 0.15)},
        profiles=(fwdfit.Profile("boa_d01.1mm", 1.1, "white", "boa", grid(72.0)),
                  fwdfit.Profile("boa_d10.0mm", 10.0, "white", "boa", grid(180.0)),
                  fwdfit.Profile("icon_d01.1mm", 1.1, "l40", "icon", grid(72.0))),
        fit=fwdfit.FitSpec(()))


def _spectrum_table(spectrum):
    if isinstance(spectrum, GaussianLine):
        lam = np.linspace(*spectrum.support_A, 801)
        return lam, spectrum.density(lam)
    return np.asarray(spectrum.lambda_A), np.asarray(spectrum.weight)


def make(case: str) -> None:
    sample, tilt = case.split("_tilt")
    fresnel = tilt.endswith("_fresnel")
    folder = HERE / case
    folder.mkdir(exist_ok=True)
    scene = fwdfit.scene.load_scene(fwdfit.scene.save_scene(
        scene_of(sample, float(tilt.removesuffix("_fresnel")), fresnel), folder / "scene.toml"))
    layers = [ReferenceLayer(l.thickness_um, l.sld_e6_per_A2, l.mu_per_m, l.mu_per_m_per_A)
              for l in scene.sample.layers]
    log = {"tracer": "fwdfit.reference.trace_reference", "n_batches": N_BATCHES, "fresnel": fresnel,
           "profiles": []}
    for i, profile in enumerate(scene.profiles):
        instrument = scene.instruments[profile.instrument]
        lam, weight = _spectrum_table(scene.spectra[profile.spectrum])
        edges = np.append(profile.x_um - 0.5 * instrument.pixel_um, profile.x_um[-1] + 0.5 * instrument.pixel_um)
        start = time.perf_counter()
        ref = trace_reference(layers, depth_mm=scene.sample.depth_mm, tilt_deg=scene.sample.tilt_deg,
                              centre_um=scene.sample.centre_um, aperture=instrument.aperture,
                              aperture_mm=instrument.aperture_mm,
                              aperture_distance_m=instrument.aperture_distance_m,
                              distance_mm=profile.distance_mm, spectrum_lambda_A=lam, spectrum_weight=weight,
                              pixel_edges_um=edges, n_rays=N_RAYS[profile.distance_mm], seed=SEED + i,
                              n_batches=N_BATCHES, fresnel=fresnel)
        elapsed = time.perf_counter() - start
        np.savetxt(folder / f"{profile.name}.csv",
                   np.column_stack([profile.x_um, ref.T, ref.T_err, ref.T_att, ref.T_att_err]),
                   delimiter=",", fmt="%.7g", header="x_um,T,T_err,T_att,T_att_err", comments="")
        log["profiles"].append({"name": profile.name, "n_rays": N_RAYS[profile.distance_mm], "seed": SEED + i,
                                "elapsed_s": round(elapsed, 1), "n_dropped": ref.n_dropped,
                                "rms_T_err": float(np.sqrt(np.mean(ref.T_err ** 2))),
                                "max_T_err": float(np.max(ref.T_err))})
        print(case, profile.name, f"{elapsed:.0f} s", log["profiles"][-1]["rms_T_err"], flush=True)
    (folder / "case.json").write_text(json.dumps(log, indent=1) + "\n")


CASES = [f"{s}_tilt{t}{f}" for f in ("", "_fresnel") for s in ("skin2", "skin1.2", "ti4") for t in ("0", "0.24")]

if __name__ == "__main__":
    for name in sys.argv[1:] or CASES:
        make(name)

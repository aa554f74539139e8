"""Make the data of notebook 07: a graded coating on Al whose coating | Al interface is rough.

A 150 µm coating whose SLD falls from 3.0 to 1.6 (1e-6 Å^-2) and mu from 400 to 120 /m
across it (a porous oxide drying towards the metal), on 850 µm of Al (SLD 2.078, mu 1.39 /m).
The coating | Al interface has an RMS normal slope of 3 mrad; the outer face is sharp.
ICON-like 4.6 Å line (15 % FWHM), circular 40 mm aperture at 5.5 m, tilt 0.24°, 2 mm deep,
distances 1.1 and 10 mm, 2.4 µm pixels over the coating's side (x -580 to -280 µm).

Exact Monte Carlo tracer (``fwdfit.reference.trace_reference``: the gradient as 50
sublayers, a normal drawn for every crossing of the rough interface), 8 000 rays per µm of
its aim window (about 4 million per profile, seed 700 + profile index), plus 0.5 %
Gaussian noise (numpy seed 7). Writes into ``graded_rough/``: one CSV per distance
(x_um, T, T_err, T_att), ``truth.json`` and ``case.json`` (rays, seeds, tracer noise).

Run from the repository root: ``python3 notebooks/data/make_graded_rough.py`` (about a
minute on 2 cores).
"""

import json
import time
from pathlib import Path

import numpy as np

import fwdfit
from fwdfit.reference import ReferenceLayer, trace_reference

OUT = Path(__file__).resolve().parent / "graded_rough"
ROUGHNESS_MRAD = 3.0
NOISE = 0.005
RAYS_PER_UM = 8_000
SEED = 700
LINE = fwdfit.GaussianLine(4.6, 0.15)
TRUTH = {"layers.coating.thickness_um": 150.0, "layers.coating.sld_e6_per_A2": 3.0,
         "layers.coating.sld_end_e6_per_A2": 1.6, "layers.coating.mu_per_m": 400.0,
         "layers.coating.mu_end_per_m": 120.0, "layers.coating.roughness_mrad": ROUGHNESS_MRAD,
         "sample.tilt_deg": 0.24, "sample.centre_um": 0.0}


def main() -> None:
    OUT.mkdir(exist_ok=True)
    layers = [ReferenceLayer(150.0, 3.0, 400.0, 0.0, roughness_mrad=ROUGHNESS_MRAD,
                             sld_end_e6_per_A2=1.6, mu_end_per_m=120.0),
              ReferenceLayer(850.0, 2.078, 1.39, 0.0)]
    pixel = 2.4
    x_um = np.arange(-580.0, -280.0, pixel) + 0.5 * pixel
    edges = np.append(x_um - 0.5 * pixel, x_um[-1] + 0.5 * pixel)
    lam = np.linspace(*LINE.support_A, 801)
    rng = np.random.default_rng(7)
    log = {"tracer": "fwdfit.reference.trace_reference", "graded_sublayers": 50, "noise": NOISE, "profiles": []}
    for i, distance_mm in enumerate((1.1, 10.0)):
        aim_um = edges[-1] - edges[0] + 2 * (0.02 * (1e3 * distance_mm + 1e3) + 50.0)
        n_rays = int(RAYS_PER_UM * aim_um)
        start = time.perf_counter()
        ref = trace_reference(layers, depth_mm=2.0, tilt_deg=0.24, centre_um=0.0, aperture="circular",
                              aperture_mm=40.0, aperture_distance_m=5.5, distance_mm=distance_mm,
                              spectrum_lambda_A=lam, spectrum_weight=LINE.density(lam), pixel_edges_um=edges,
                              n_rays=n_rays, seed=SEED + i, n_batches=10, graded_sublayers=50)
        T = ref.T + rng.normal(0.0, NOISE, ref.T.size)
        T_err = np.hypot(NOISE, ref.T_err)
        name = f"d{distance_mm:04.1f}mm"
        np.savetxt(OUT / f"{name}.csv", np.column_stack([x_um, T, T_err, ref.T_att]), delimiter=",",
                   fmt="%.8g", header="x_um,T,T_err,T_att", comments="")
        log["profiles"].append({"name": name, "distance_mm": distance_mm, "n_rays": n_rays, "seed": SEED + i,
                                "elapsed_s": round(time.perf_counter() - start, 1),
                                "rms_tracer_T_err": float(np.sqrt(np.mean(ref.T_err ** 2)))})
        print(name, f"{time.perf_counter() - start:.0f} s", flush=True)
    (OUT / "truth.json").write_text(json.dumps(TRUTH, indent=1) + "\n")
    (OUT / "case.json").write_text(json.dumps(log, indent=1) + "\n")


if __name__ == "__main__":
    main()

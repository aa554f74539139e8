"""Make the data of the cladding notebook: one wall of a Zircaloy tube with an oxide rim outside
and a hydride rim inside.

A tube of outer radius 4750 µm (the axis vertical, along the detector's columns) whose 570 µm
wall is, from the outside in, ZrO2 20 µm | Zircaloy 520 µm | a delta-ZrH1.6-like hydride 30 µm,
and a vacuum bore (inner radius 4180 µm). Material constants are explicit (SLD 1e-6 Å^-2,
mu(λ) = mu_per_m + mu_per_m_per_A·λ per metre; see MATERIALS below for how they were
estimated). BOA-like instrument: square 40 mm aperture at 7.5 m, Maxwellian white beam
(T = 47.25 K, 0.8-10 Å), no detector blur; the axis 8.5 and 20.0 mm from the detector;
2.4 µm pixels over the right-hand wall only, x = 3900 to 5400 µm from the axis' projection
(the bore's edge, the wall, the rim and the light the rim throws outside).

Exact tracer ``fwdfit.reference.trace_cylinder_reference`` (independent of the fast model;
its deterministic quadrature, 32 wavelengths x 256 aperture points x 4 batches, seed 900 +
profile index), plus 0.5 % Gaussian noise (numpy seed 9). Writes into ``cladding/``: one CSV
per distance (x_um, T, T_err, T_att), ``truth.json`` and ``case.json`` (nodes, seeds, times,
the tracer's own noise).

Run from the repository root: ``python3 notebooks/data/make_cladding.py`` (about a minute or
two on 2 cores).
"""

import json
import time
from pathlib import Path

import numpy as np

from fwdfit.reference import ReferenceLayer, maxwellian_spectrum, trace_cylinder_reference

OUT = Path(__file__).resolve().parent / "cladding"
NOISE = 0.005
SEED = 900
OUTER_RADIUS_UM = 4750.0
# Explicit constants: SLD = N Σb; mu = N Σσ with the scattering counted as a loss and 1/v
# absorption (σ_a at 1.798 Å). Zircaloy as Zr (6.56 g/cm³): N = 0.0433 Å^-3, b = 7.16 fm,
# σ_s = 6.46 b, σ_a = 0.185 b. ZrO2 (5.68 g/cm³): N = 0.0278 Å^-3, Σb = 18.77 fm,
# Σσ_s = 14.9 b. delta-ZrH1.6 (5.6 g/cm³): N = 0.0363 Å^-3, Σb = 7.16 - 1.6 x 3.739 fm,
# Σσ_s = 6.46 + 1.6 x 82 b (hydrogen's incoherent cross section, bound, cold neutrons).
MATERIALS = {
    "oxide": ReferenceLayer(20.0, 5.21, 41.4, 0.03),
    "zircaloy": ReferenceLayer(520.0, 3.10, 28.0, 0.45),
    "hydride": ReferenceLayer(30.0, 0.43, 500.0, 0.38),
}
TRUTH = {"sample.outer_radius_um": OUTER_RADIUS_UM, "sample.core": "vacuum", "sample.centre_um": 0.0,
         **{f"layers.{name}.{key}": getattr(layer, key) for name, layer in MATERIALS.items()
            for key in ("thickness_um", "sld_e6_per_A2", "mu_per_m", "mu_per_m_per_A")}}
NODES = dict(n_wavelengths=32, n_aperture=256, n_batches=4)


def main() -> None:
    OUT.mkdir(exist_ok=True)
    pixel = 2.4
    x_um = np.arange(3900.0, 5400.0, pixel) + 0.5 * pixel
    edges = np.append(x_um - 0.5 * pixel, x_um[-1] + 0.5 * pixel)
    lam, weight = maxwellian_spectrum(47.25, 0.8, 10.0)
    rng = np.random.default_rng(9)
    log = {"tracer": "fwdfit.reference.trace_cylinder_reference", "method": "quadrature", **NODES,
           "instrument": {"aperture": "square", "aperture_mm": 40.0, "aperture_distance_m": 7.5,
                          "pixel_um": pixel, "psf_fwhm_um": 0.0},
           "spectrum": {"maxwellian_T_K": 47.25, "lambda_min_A": 0.8, "lambda_max_A": 10.0},
           "noise": NOISE, "noise_seed": 9, "profiles": []}
    for i, distance_mm in enumerate((8.5, 20.0)):
        start = time.perf_counter()
        ref = trace_cylinder_reference(
            list(MATERIALS.values()), outer_radius_um=OUTER_RADIUS_UM, core="vacuum", centre_um=0.0,
            aperture="square", aperture_mm=40.0, aperture_distance_m=7.5, distance_mm=distance_mm,
            spectrum_lambda_A=lam, spectrum_weight=weight, pixel_edges_um=edges, seed=SEED + i, **NODES)
        T = ref.T + rng.normal(0.0, NOISE, ref.T.size)
        T_err = np.hypot(NOISE, ref.T_err)
        name = f"d{distance_mm:04.1f}mm"
        np.savetxt(OUT / f"{name}.csv", np.column_stack([x_um, T, T_err, ref.T_att]), delimiter=",",
                   fmt="%.8g", header="x_um,T,T_err,T_att", comments="")
        log["profiles"].append({"name": name, "distance_mm": distance_mm, "seed": SEED + i,
                                "rays_traced": ref.n_rays, "rays_dropped": ref.n_dropped,
                                "elapsed_s": round(time.perf_counter() - start, 1),
                                "rms_tracer_T_err": float(np.sqrt(np.mean(ref.T_err ** 2))),
                                "max_tracer_T_err": float(np.max(ref.T_err))})
        print(name, f"{time.perf_counter() - start:.0f} s", flush=True)
    (OUT / "truth.json").write_text(json.dumps(TRUTH, indent=1) + "\n")
    (OUT / "case.json").write_text(json.dumps(log, indent=1) + "\n")


if __name__ == "__main__":
    main()

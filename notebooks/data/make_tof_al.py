"""Make the time-of-flight data of notebook 06: the Al block in 24 wavelength bins (3-6 Å).

Exact Monte Carlo tracer (``fwdfit.reference.trace_reference``) fed NCrystal's own
cross-sections for Al_sg225 (mu(lambda) with its Bragg edges, density x 0.97) and the
coherent SLD from NCrystal's composition, 4 000 000 rays per bin (seed = bin index),
plus 1 % Gaussian noise (numpy seed 7). Writes into ``tof_al/``: one CSV per bin
(x_um, T, T_err), the tracer's attenuation-only profiles (``attenuation_only.csv``,
one column per bin), the true values (``truth.json``) and ``scene.toml`` (the fit's
starting point: thickness +20 µm, tilt +0.06°, centre -3 µm, density scale 1).

Run from the repository root: ``python3 notebooks/data/make_tof_al.py`` (about three minutes on 2 cores).
"""

import json
from pathlib import Path

import NCrystal
import numpy as np

from fwdfit.reference import ReferenceLayer, trace_reference

OUT = Path(__file__).resolve().parent / "tof_al"
CFG = "Al_sg225.ncmat"
TRUTH = {"layers.Al.thickness_um": 1000.0, "sample.tilt_deg": 0.24, "sample.centre_um": 3.0,
         "layers.Al.density_scale": 0.97}
GEOMETRY = dict(depth_mm=2.0, aperture="square", aperture_mm=40.0, aperture_distance_m=7.5,
                distance_mm=8.5)  # BOA-like pinhole, as the McStas Al block
PIXEL_UM = 2.4
N_PIXELS = 600
BINS_A = np.linspace(3.0, 6.0, 25)
NOISE = 0.01
N_RAYS = 4_000_000  # the tracer's own noise at the faces: 0.4 % per pixel (0.8 % at 10^6)

SCENE_HEAD = f"""# Time-of-flight Al block, made by make_tof_al.py (exact tracer + NCrystal, 1 % noise)
[sample]
depth_mm = {GEOMETRY["depth_mm"]}
tilt_deg = 0.3
centre_um = 0.0

[[sample.layers]]
name = "Al"
thickness_um = 1020.0
ncrystal = "{CFG}"

[instrument]
aperture = "{GEOMETRY["aperture"]}"
aperture_mm = {GEOMETRY["aperture_mm"]}
aperture_distance_m = {GEOMETRY["aperture_distance_m"]}
pixel_um = {PIXEL_UM}

[fit]
vary = ["layers.Al.thickness_um", "sample.tilt_deg", "sample.centre_um", "layers.Al.density_scale"]
"""


def ncrystal_mu_per_m(wavelength_A: np.ndarray) -> np.ndarray:
    """NCrystal's total scattering + absorption cross-section x number density, 1/m."""
    material = NCrystal.load(CFG)
    barn = material.scatter.xsect(wl=wavelength_A) + material.absorption.xsect(wl=wavelength_A)
    return 100.0 * material.info.numberdensity * np.asarray(barn)  # barn / Å^3 = 1/cm


def main() -> None:
    OUT.mkdir(exist_ok=True)
    info = NCrystal.createInfo(CFG)
    scale = TRUTH["layers.Al.density_scale"]
    sld = scale * 1e6 * info.numberdensity * 1e-5 * info.composition[0][1].coherentScatLenFM()
    layer = ReferenceLayer(TRUTH["layers.Al.thickness_um"], sld, 0.0, 0.0,
                           lambda lam: scale * ncrystal_mu_per_m(lam))
    x_um = PIXEL_UM * (np.arange(N_PIXELS) - 0.5 * (N_PIXELS - 1))
    edges_um = np.append(x_um - 0.5 * PIXEL_UM, x_um[-1] + 0.5 * PIXEL_UM)
    rng = np.random.default_rng(7)
    parts, att = [SCENE_HEAD], [x_um]
    for i, (lo, hi) in enumerate(zip(BINS_A[:-1], BINS_A[1:])):
        name = f"b{i:02d}"
        reference = trace_reference(
            [layer], tilt_deg=TRUTH["sample.tilt_deg"], centre_um=TRUTH["sample.centre_um"],
            spectrum_lambda_A=np.array([lo, hi]), spectrum_weight=np.ones(2),
            pixel_edges_um=edges_um, n_rays=N_RAYS, seed=i, **GEOMETRY)
        att.append(reference.T_att)
        T = reference.T + NOISE * rng.standard_normal(N_PIXELS)
        np.savetxt(OUT / f"{name}.csv", np.column_stack([x_um, T, np.full(N_PIXELS, NOISE)]),
                   delimiter=",", header="x_um,T,T_err", comments="", fmt="%.6g")
        parts.append(f"[spectra.{name}]\nlambda_min_A = {lo:.4f}\nlambda_max_A = {hi:.4f}\n\n"
                     f'[[profiles]]\nname = "{name}"\ndistance_mm = {GEOMETRY["distance_mm"]}\n'
                     f'spectrum = "{name}"\nfile = "{name}.csv"\n')
        print(name, f"{lo:.3f}-{hi:.3f} Å", flush=True)
    header = ",".join(["x_um"] + [f"b{i:02d}" for i in range(len(BINS_A) - 1)])
    np.savetxt(OUT / "attenuation_only.csv", np.column_stack(att), delimiter=",", header=header,
               comments="", fmt="%.6g")
    (OUT / "scene.toml").write_text("\n".join(parts))
    (OUT / "truth.json").write_text(json.dumps(TRUTH, indent=1) + "\n")


if __name__ == "__main__":
    main()

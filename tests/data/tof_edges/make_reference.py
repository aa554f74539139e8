"""Make tof_edges.npz: 24 time-of-flight bins of an Al block across the 4.68 Å Bragg edge,
traced with the exact Monte Carlo tracer (``fwdfit.reference.trace_reference``) fed NCrystal's
own cross-sections, plus 1 % Gaussian noise; for the start finder's test (tests/test_tof_scaling.py).

    python tests/data/tof_edges/make_reference.py   (about 2 min on 2 cores; needs NCrystal)

Al_sg225.ncmat block 800 µm thick, 3 mm deep, tilt 0.1°, centre 4 µm; circular aperture
25 mm at 9 m, detector at 12 mm, 2.4 µm pixels, no blur; 24 bins tiling 4.2-5.2 Å; 1.5e6
rays per bin (seeds 11000 + bin), noise seed 11. Stored float32: x_um (n,), T (24, n),
lambda_edges_A (25,), and the truth.
"""
from pathlib import Path

import numpy as np

import fwdfit
from fwdfit.reference import ReferenceLayer, trace_reference

AL = "Al_sg225.ncmat"
TRUTH = dict(thickness_um=800.0, tilt_deg=0.1, centre_um=4.0, depth_mm=3.0, distance_mm=12.0,
             aperture_mm=25.0, aperture_distance_m=9.0, pixel_um=2.4)


def main():
    import NCrystal

    material, info = NCrystal.load(AL), NCrystal.createInfo(AL)

    def mu_per_m(lam):
        barn = material.scatter.xsect(wl=lam) + material.absorption.xsect(wl=lam)
        return 100.0 * info.numberdensity * np.asarray(barn)

    sld = 1e6 * info.numberdensity * 1e-5 * info.composition[0][1].coherentScatLenFM()
    layer = ReferenceLayer(TRUTH["thickness_um"], sld, 0.0, 0.0, mu_per_m)
    x_um = fwdfit.pixel_grid(-700.0, 700.0, TRUTH["pixel_um"])
    edges_um = np.append(x_um - 1.2, x_um[-1] + 1.2)
    bins = np.linspace(4.2, 5.2, 25)
    rng = np.random.default_rng(11)
    T = []
    for i, (lo, hi) in enumerate(zip(bins[:-1], bins[1:])):
        ref = trace_reference([layer], depth_mm=TRUTH["depth_mm"], tilt_deg=TRUTH["tilt_deg"],
                              centre_um=TRUTH["centre_um"], aperture="circular", aperture_mm=TRUTH["aperture_mm"],
                              aperture_distance_m=TRUTH["aperture_distance_m"], distance_mm=TRUTH["distance_mm"],
                              spectrum_lambda_A=np.array([lo, hi]), spectrum_weight=np.ones(2),
                              pixel_edges_um=edges_um, n_rays=1_500_000, seed=11000 + i)
        T.append(ref.T + 0.01 * rng.standard_normal(x_um.size))
    np.savez_compressed(Path(__file__).with_name("tof_edges.npz"), x_um=x_um.astype(np.float32),
                        T=np.array(T, np.float32), lambda_edges_A=bins,
                        **{k: np.float64(v) for k, v in TRUTH.items()})


if __name__ == "__main__":
    main()

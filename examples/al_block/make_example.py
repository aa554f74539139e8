"""Generate the shipped Al-block example with fwdfit's exact Monte Carlo reference.

    python examples/al_block/make_example.py        # rewrites the *.csv profiles here

Truth: a 1000 µm Al block (2 mm deep, periodictable constants for Al at 2.70 g/cm3),
tilted by 0.24 deg, centred at x = 3 µm; BOA white beam at 1.1, 8.5 and 34.4 mm and
ICON lines at 2.7 and 4.6 Å (1.1 mm). Each profile is traced with 4e6 rays (exact
Snell, float64) and Gaussian noise of 0.5 % is added (seed 2026); T_err = 0.005.
scene.toml starts the fit away from this truth.
"""

from pathlib import Path

import numpy as np

import fwdfit

HERE = Path(__file__).parent
TRUTH = dict(thickness_um=1000.0, tilt_deg=0.24, centre_um=3.0)
NOISE = 0.005
RAYS = 4_000_000


def main() -> None:
    scene = fwdfit.load_scene(HERE / "scene.toml")
    al = fwdfit.constants_from_formula("Al", 2.70)
    layer = fwdfit.ReferenceLayer(TRUTH["thickness_um"], al.sld_e6_per_A2, al.mu_per_m, al.mu_per_m_per_A)
    rng = np.random.default_rng(2026)
    for i, profile in enumerate(scene.profiles):
        instrument = scene.instruments[profile.instrument]
        spectrum = scene.spectra[profile.spectrum]
        lam = np.linspace(*spectrum.support_A, 2000)
        edges = np.append(profile.x_um - 0.5 * instrument.pixel_um, profile.x_um[-1] + 0.5 * instrument.pixel_um)
        traced = fwdfit.trace_reference(
            [layer], depth_mm=scene.sample.depth_mm, tilt_deg=TRUTH["tilt_deg"], centre_um=TRUTH["centre_um"],
            aperture=instrument.aperture, aperture_mm=instrument.aperture_mm,
            aperture_distance_m=instrument.aperture_distance_m, distance_mm=profile.distance_mm,
            spectrum_lambda_A=lam, spectrum_weight=spectrum.density(lam), pixel_edges_um=edges,
            n_rays=RAYS, seed=i)
        T = traced.T + rng.normal(0.0, NOISE, traced.T.shape)
        table = np.column_stack([profile.x_um, T, np.full_like(T, NOISE), traced.T_att])
        np.savetxt(HERE / f"{profile.name}.csv", table, delimiter=",", fmt="%.7g",
                   header="x_um,T,T_err,T_att_true", comments="")
        print(f"{profile.name}: {traced.n_rays} rays")


if __name__ == "__main__":
    main()

"""Generate the shipped image examples with fwdfit's exact Monte Carlo reference.

    python examples/images/make_images.py        # rewrites the *.tif files here

Truth: a 1000 µm Al block (2 mm deep, periodictable constants for Al at 2.70 g/cm3),
tilted by 0.24 deg, at ICON (circular 40 mm aperture at 5.5 m, 2.7 Å line, 15 % FWHM),
8.5 mm from the detector, 2.4 µm pixels; 500 pixels per row from x = -600 µm. Each file
comes from one trace of 4e7 rays (exact Snell, float64; ``fwdfit.trace_reference_rows``).

- ``T.tif`` (for ``fwdfit fit-image scene.toml``): 32 rows, the block's centre curving
  across them (4 + 6 sin(2 pi row / 32) µm), Gaussian noise of 0.5 % (seed 2026), float32.
  Al's attenuation step is 1.8 %, its refraction peaks beside each face about 5 %.
- ``sample.tif``, ``open.tif``, ``dark.tif`` (for ``fwdfit profile``): 64 rows, the block
  centred at 3 µm in every row; frames of uint16 counts, dark 100, open beam 4000 above it,
  Poisson noise (seed 2027): three sample frames, three open-beam frames, two dark frames.

scene.toml starts the image fit away from the truth (1100 µm, tilt 0.15°).
"""

from pathlib import Path

import numpy as np
import tifffile

import fwdfit

HERE = Path(__file__).parent
X0_UM, PIXEL_UM, N_COLS = -600.0, 2.4, 500
RAYS = 40_000_000
DARK, OPEN = 100.0, 4000.0


def traced(centres_um: np.ndarray) -> np.ndarray:
    """T (rows, N_COLS) of the block at the given centres (rows,) µm."""
    al = fwdfit.constants_from_formula("Al", 2.70)
    lam = np.linspace(2.7 * (1 - 0.3), 2.7 * (1 + 0.3), 2001)
    weight = np.exp(-0.5 * ((lam - 2.7) / (0.15 * 2.7 / 2.3548)) ** 2)
    reference = fwdfit.trace_reference_rows(
        [fwdfit.ReferenceLayer(1000.0, al.sld_e6_per_A2, al.mu_per_m, al.mu_per_m_per_A)],
        centres_um=centres_um, x0_um=X0_UM, pixel_um=PIXEL_UM, n_pixels=N_COLS, depth_mm=2.0, tilt_deg=0.24,
        aperture="circular", aperture_mm=40.0, aperture_distance_m=5.5, distance_mm=8.5,
        spectrum_lambda_A=lam, spectrum_weight=weight, n_rays=RAYS, seed=1)
    return reference.T


def main() -> None:
    rows = np.arange(32)
    T = traced(4.0 + 6.0 * np.sin(2 * np.pi * rows / len(rows)))
    image = T + np.random.default_rng(2026).normal(0.0, 0.005, T.shape)
    tifffile.imwrite(HERE / "T.tif", image.astype(np.float32))
    T = traced(np.full(64, 3.0))
    rng = np.random.default_rng(2027)
    for name, level, n in (("sample", DARK + OPEN * T, 3), ("open", np.full(T.shape, DARK + OPEN), 3),
                           ("dark", np.full(T.shape, DARK), 2)):
        with tifffile.TiffWriter(HERE / f"{name}.tif") as stack:  # one page per frame
            for _ in range(n):
                stack.write(rng.poisson(level).astype(np.uint16))
    for name in ("T.tif", "sample.tif", "open.tif", "dark.tif"):
        print(f"{name}: {(HERE / name).stat().st_size / 1024:.0f} KiB")


if __name__ == "__main__":
    main()

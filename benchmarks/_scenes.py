"""Scene parts shared by the fit benchmarks: the BOA and ICON instruments and spectra (values)."""

from pathlib import Path

BOA_SPECTRUM = Path(__file__).resolve().parents[1] / "tests" / "data" / "mcstas" / "spectrum_boa.csv"


def instruments(pixel_um: float = 2.4) -> dict:
    """BOA (the default instrument) and ICON (``icon``)."""
    import fwdfit

    return {"": fwdfit.Instrument("square", 40.0, 7.5, pixel_um),
            "icon": fwdfit.Instrument("circular", 40.0, 5.5, pixel_um)}


def spectra(lines: dict[str, float]) -> dict:
    """The BOA white beam ``white`` and the Gaussian lines ``lines`` (spectrum name:
    wavelength in Å, 15 % FWHM)."""
    import numpy as np

    import fwdfit

    lam, weight = np.loadtxt(BOA_SPECTRUM, delimiter=",", skiprows=1, unpack=True)
    return {"white": fwdfit.TabulatedSpectrum(lam, weight, BOA_SPECTRUM),
            **{name: fwdfit.GaussianLine(wavelength_A, 0.15) for name, wavelength_A in lines.items()}}

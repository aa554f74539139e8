"""Scene text shared by the fit benchmarks: the BOA and ICON instruments and spectra."""

from pathlib import Path

BOA_SPECTRUM = Path(__file__).resolve().parents[1] / "tests" / "data" / "mcstas" / "spectrum_boa.csv"


def instruments_toml(lines: dict[str, float], pixel_um: float = 2.4) -> str:
    """BOA (default instrument, white beam ``white``) and ICON (``icon``) with the
    Gaussian lines ``lines`` (spectrum name: wavelength in Å, 15 % FWHM)."""
    text = (f'[instrument]\naperture = "square"\naperture_mm = 40.0\naperture_distance_m = 7.5\n'
            f'pixel_um = {pixel_um}\n\n[instruments.icon]\naperture = "circular"\naperture_mm = 40.0\n'
            f'aperture_distance_m = 5.5\npixel_um = {pixel_um}\n\n[spectra.white]\nfile = "{BOA_SPECTRUM}"\n')
    for name, wavelength_A in lines.items():
        text += f'\n[spectra."{name}"]\nwavelength_A = {wavelength_A}\nfwhm_rel = 0.15\n'
    return text

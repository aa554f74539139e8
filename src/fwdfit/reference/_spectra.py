"""Tabulated spectra for the reference tracers (which sample any table, linear between rows)."""

from __future__ import annotations

import numpy as np

from .._errors import FwdfitError

_A_KELVIN_A2 = 949.0  # h² / (2 m_n k_B) in K·Å², as McStas's Source_gen uses it


def maxwellian_spectrum(temperature_K: float, lambda_min_A: float, lambda_max_A: float,
                        step_A: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """A Maxwellian flux spectrum w(λ) = 2 a² exp(-a/λ²) / λ⁵, a = 949 K·Å² / T, cut to [λmin, λmax].

    Args:
        temperature_K: moderator temperature T (K).
        lambda_min_A, lambda_max_A: the band (Å), 0 < min < max.
        step_A: table spacing (Å); the tracers interpolate linearly between rows.

    Returns:
        (lambda_A, weight), each (n_rows,), for ``spectrum_lambda_A`` and ``spectrum_weight``.
    """
    if not (temperature_K > 0 and 0 < lambda_min_A < lambda_max_A and step_A > 0):
        raise FwdfitError("need temperature_K > 0, 0 < lambda_min_A < lambda_max_A and step_A > 0")
    n = max(int(np.ceil((lambda_max_A - lambda_min_A) / step_A)), 1) + 1
    lam = np.linspace(lambda_min_A, lambda_max_A, n)
    a = _A_KELVIN_A2 / temperature_K
    return lam, 2.0 * a * a * np.exp(-a / lam**2) / lam**5

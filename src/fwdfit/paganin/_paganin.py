"""The neutron Paganin-type filter of the paper: the single-material baseline.

The filter inverts the homogeneous-object transport-of-intensity relation
``T_meas = (1 - tau * laplacian) T_att``, i.e. ``F[T_meas] = (1 + tau k^2) F[T_att]``:

    T_filtered = F^-1[ F[T] / (1 + tau k^2) ],   thickness = -log(T_filtered) / mu.

The paper writes ``tau = lambda^2 b_coh Delta / (2 pi sigma) - (Theta Delta)^2 / 8``.
For units of length^2 the first term needs the scattering length *density*
``SLD = N b_coh`` and ``sigma = mu = N sigma_total`` (1/length); it is then
``delta * Delta / mu`` with ``delta = lambda^2 SLD / (2 pi)`` the refractive
decrement, as in Paganin's X-ray filter. Implemented, in these units:

    tau [um^2] = b_factor * (lambda[A]^2 * SLD[A^-2] / (2 pi)) * (Delta[mm] * 1e3)
                 / (mu[1/m] * 1e-6)  -  (Theta[rad] * Delta[mm] * 1e3)^2 / 8

with ``Theta = D / L`` the full beam divergence. Inside the filter lengths are
in um and the frequencies ``k = 2 pi fftfreq(n, d=pixel_um)`` in rad/um.
"""

import math

import numpy as np

from .._errors import FwdfitError

# Edge padding per side, in decay lengths sqrt(tau) of the filter kernel
# exp(-|x| / sqrt(tau)): the wrap-around leaks in as exp(-10) ~ 5e-5 of the jump.
_PAD_DECAY_LENGTHS = 10.0
# regularise=True: the denominator is max(1 + tau k^2, 0.01), so no frequency
# is amplified more than 100-fold when tau < 0.
_DENOMINATOR_FLOOR = 1e-2


def paganin_tau_um2(*, wavelength_A, sld_e6_per_A2, mu_per_m, distance_mm, divergence_rad,
                    b_factor=1.0):
    """Filter parameter tau in um^2 (formula in the module docstring); arrays broadcast.

    Args:
        wavelength_A: neutron wavelength lambda, Å (> 0).
        sld_e6_per_A2: coherent scattering length density N b_coh, 1e-6 Å^-2 (Al: 2.078).
        mu_per_m: total attenuation coefficient N sigma_total, 1/m (> 0).
        distance_mm: sample-detector distance Delta, mm (>= 0).
        divergence_rad: full beam divergence Theta = D / L, rad (>= 0).
        b_factor: multiplies the SLD (the paper used 40).

    Returns tau, um^2; may be <= 0, where the filters refuse it.
    """
    lam = _checked("wavelength_A", wavelength_A, lower=0.0, strict=True)
    mu = _checked("mu_per_m", mu_per_m, lower=0.0, strict=True)
    distance_um = 1e3 * _checked("distance_mm", distance_mm, lower=0.0)
    theta = _checked("divergence_rad", divergence_rad, lower=0.0)
    sld = _checked("sld_e6_per_A2", sld_e6_per_A2) * _checked("b_factor", b_factor)
    delta = lam**2 * (1e-6 * sld) / (2 * math.pi)  # Å^2 * Å^-2: dimensionless
    tau = delta * distance_um / (1e-6 * mu) - (theta * distance_um) ** 2 / 8
    return tau[()]


def paganin_tau_um2_spectrum(*, wavelength_A, weight, sld_e6_per_A2, mu_per_m, distance_mm,
                             divergence_rad, mu_per_m_per_A=0.0, b_factor=1.0,
                             mode="mean_wavelength"):
    """Filter parameter tau in um^2 for a spectrum, mu(lambda) = mu_per_m + mu_per_m_per_A * lambda.

    Args:
        wavelength_A, weight: shape (n,) spectrum table, Å and relative detected counts (>= 0).
        mode: "mean_wavelength" (the paper's choice for BOA): tau at the weighted mean
            wavelength sum(w lambda) / sum(w), with mu at that wavelength.
            "weighted_tau": sum(w tau(lambda)) / sum(w), with mu(lambda) per wavelength.
        Others as in `paganin_tau_um2`; distance_mm may be an array of shape (m,).

    Returns tau, um^2, a float or shape (m,).
    """
    lam = _checked("wavelength_A", wavelength_A, lower=0.0, strict=True)
    w = _checked("weight", weight, lower=0.0)
    if lam.ndim != 1 or lam.shape != w.shape or not w.sum() > 0:
        raise FwdfitError("spectrum: wavelength_A and weight must be 1-D of equal length "
                          "with a positive total weight")
    mu_slope = _checked("mu_per_m_per_A", mu_per_m_per_A)
    common = dict(sld_e6_per_A2=sld_e6_per_A2, divergence_rad=divergence_rad, b_factor=b_factor)
    if mode == "mean_wavelength":
        lam_mean = np.average(lam, weights=w)
        return paganin_tau_um2(wavelength_A=lam_mean, mu_per_m=mu_per_m + mu_slope * lam_mean,
                               distance_mm=distance_mm, **common)
    if mode == "weighted_tau":
        tau = paganin_tau_um2(wavelength_A=lam, mu_per_m=mu_per_m + mu_slope * lam,
                              distance_mm=np.asarray(distance_mm, float)[..., None], **common)
        return np.average(tau, weights=w, axis=-1)[()]
    raise FwdfitError(f"spectrum: unknown mode {mode!r} (use 'mean_wavelength' or 'weighted_tau')")


def paganin_filter_1d(T, pixel_um, tau_um2, *, pad="edge", regularise=False):
    """Filtered transmission F^-1[F[T] / (1 + tau k^2)] of a profile.

    Args:
        T: shape (n,) transmission profile.
        pixel_um: pixel size, um (> 0).
        tau_um2: filter parameter, um^2 (> 0 unless regularise).
        pad: "edge" (repeat the end values, against wrap-around) or "periodic" (none).
        regularise: allow tau <= 0, clamping the denominator at 0.01.

    Returns shape (n,) filtered transmission.
    """
    return _filter(_image(T, 1), pixel_um, tau_um2, pad, regularise)


def paganin_filter_2d(image, pixel_um, tau_um2, *, pad="edge", regularise=False):
    """`paganin_filter_1d` for a shape (ny, nx) image of square pixels, k^2 = kx^2 + ky^2."""
    return _filter(_image(image, 2), pixel_um, tau_um2, pad, regularise)


def paganin_thickness_um(T, pixel_um, tau_um2, mu_per_m, *, pad="edge", regularise=False):
    """Single-material thickness -log(T_filtered) / mu in um, for a profile (n,) or image (ny, nx)."""
    mu = _checked("mu_per_m", mu_per_m, lower=0.0, strict=True)
    T = np.asarray(T, dtype=float)
    filtered = _filter(_image(T, 2 if T.ndim == 2 else 1), pixel_um, tau_um2, pad, regularise)
    if not np.all(filtered > 0):
        raise FwdfitError("Paganin filter: filtered transmission is <= 0 somewhere; "
                          "no thickness (noisy data or too large tau?)")
    return -np.log(filtered) / (1e-6 * mu)


def _filter(T, pixel_um, tau_um2, pad, regularise):
    pixel = float(_checked("pixel_um", pixel_um, lower=0.0, strict=True))
    tau = float(_checked("tau_um2", tau_um2))
    if tau <= 0 and not regularise:
        raise FwdfitError(f"Paganin filter: tau = {tau:.4g} um^2 <= 0 makes 1 + tau k^2 cross "
                          "zero (the beam-divergence term dominates); use a shorter distance or "
                          "a larger b_factor, or regularise=True")
    if pad == "edge":
        width = math.ceil(_PAD_DECAY_LENGTHS * math.sqrt(max(tau, 0.0)) / pixel)
        widths = [max(width, n // 2) for n in T.shape]
    elif pad == "periodic":
        widths = [0] * T.ndim
    else:
        raise FwdfitError(f"Paganin filter: unknown pad {pad!r} (use 'edge' or 'periodic')")
    padded = np.pad(T, [(w, w) for w in widths], mode="edge")
    freqs = [np.fft.fftfreq(n, d=pixel) for n in padded.shape[:-1]]
    freqs.append(np.fft.rfftfreq(padded.shape[-1], d=pixel))
    k2 = sum((2 * math.pi * f) ** 2 for f in np.ix_(*freqs))  # (rad/um)^2
    denominator = 1 + tau * k2
    if regularise:
        denominator = np.maximum(denominator, _DENOMINATOR_FLOOR)
    axes = tuple(range(padded.ndim))
    filtered = np.fft.irfftn(np.fft.rfftn(padded) / denominator, s=padded.shape, axes=axes)
    return filtered[tuple(slice(w, w + n) for w, n in zip(widths, T.shape))]


def _image(T, ndim):
    T = np.asarray(T, dtype=float)
    if T.ndim != ndim or T.size == 0:
        raise FwdfitError(f"Paganin filter: expected a non-empty {ndim}-D array, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise FwdfitError("Paganin filter: transmission contains NaN or inf")
    return T


def _checked(name, value, *, lower=None, strict=False):
    """value as a float64 array, finite and (optionally) > or >= lower."""
    arr = np.asarray(value, dtype=float)
    ok = np.all(np.isfinite(arr))
    if ok and lower is not None:
        ok = np.all(arr > lower) if strict else np.all(arr >= lower)
    if not ok:
        bound = "" if lower is None else f" and {'>' if strict else '>='} {lower:g}"
        raise FwdfitError(f"Paganin filter: {name} must be finite{bound}, got {value!r}")
    return arr

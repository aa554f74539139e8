"""Exact, slow Monte Carlo ray tracer in float64 NumPy: the independent reference for the forward model.

2-D geometric optics in the x-z plane (beam along +z, sample centre at z = 0, detector plane at
z = +Delta, aperture at z = -(L - Delta)). Every face crossing uses exact vector Snell's law with
total reflection (and optional Fresnel partial reflection); attenuation follows the actual path.
The open beam is the same rays without the sample (correlated sampling), so T = 1 exactly where no
traced ray lands. A rough face tilts its normal at every crossing by a Gaussian slope; a graded layer
is a stack of uniform sublayers. No JAX here on purpose: this module must stay independent of the fast model.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np

from .._errors import FwdfitError

_MAX_EVENTS = 200  # face crossings per ray before it is dropped
_CHUNK = 500_000  # rays per vectorised chunk
_MIN_DEFLECTION_RAD = 0.02  # aim-window margin: smallest deflection allowed for ...
_MARGIN_UM = 50.0  # ... plus a fixed slack (µm)
_FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))


@dataclasses.dataclass(frozen=True)
class ReferenceLayer:
    """One layer: width along x (µm), SLD (1e-6 Å^-2), mu(λ) = mu_per_m + mu_per_m_per_A·λ[Å]
    + mu_table(λ) (1/m); ``mu_table`` maps wavelengths (n,) Å to 1/m (Bragg edges), or None.

    roughness_mrad: RMS slope of the normal of the layer's right-hand face. sld_end_e6_per_A2,
    mu_end_per_m: values at the right-hand side of a graded layer (linear across; None: uniform),
    traced as ``graded_sublayers`` uniform sublayers with the values at their centres."""

    thickness_um: float
    sld_e6_per_A2: float
    mu_per_m: float
    mu_per_m_per_A: float = 0.0
    mu_table: Callable[[np.ndarray], np.ndarray] | None = None
    roughness_mrad: float = 0.0
    sld_end_e6_per_A2: float | None = None
    mu_end_per_m: float | None = None

    def sublayers(self, n: int) -> list[ReferenceLayer]:
        """The layer as n uniform sublayers (itself when uniform); only the last keeps its roughness."""
        if self.sld_end_e6_per_A2 is None and self.mu_end_per_m is None:
            return [self]
        t = (np.arange(n) + 0.5) / n
        sld_end = self.sld_e6_per_A2 if self.sld_end_e6_per_A2 is None else self.sld_end_e6_per_A2
        mu_end = self.mu_per_m if self.mu_end_per_m is None else self.mu_end_per_m
        return [dataclasses.replace(self, thickness_um=self.thickness_um / n,
                                    sld_e6_per_A2=float(self.sld_e6_per_A2 + (sld_end - self.sld_e6_per_A2) * f),
                                    mu_per_m=float(self.mu_per_m + (mu_end - self.mu_per_m) * f),
                                    roughness_mrad=self.roughness_mrad if i == n - 1 else 0.0,
                                    sld_end_e6_per_A2=None, mu_end_per_m=None)
                for i, f in enumerate(t)]


@dataclasses.dataclass(frozen=True)
class ReferenceResult:
    """(n_pixel,) transmission with refraction (T) and attenuation only (T_att), with batch errors.

    T is NaN in a pixel no open-beam ray reached, its error NaN where that happened in some batch.
    """

    T: np.ndarray
    T_err: np.ndarray
    T_att: np.ndarray
    T_att_err: np.ndarray
    n_rays: int
    n_dropped: int
    centres_um: np.ndarray | None = None  # (rows,) the stack's centre per row (trace_reference_rows)


@dataclasses.dataclass(frozen=True)
class _Stack:
    """The sample in its own frame: u across the layers (µm), w along the depth (µm)."""

    bounds_um: np.ndarray  # (K+1,) layer faces along u, centred on 0
    half_depth_um: float
    sld_over_pi: np.ndarray  # (K+1,) SLD/π in Å^-2; index K is the vacuum outside
    mu0_per_um: np.ndarray  # (K+1,)
    mu1_per_um_per_A: np.ndarray  # (K+1,)
    slope_rms_rad: np.ndarray  # (K+1,) RMS normal slope of each face (bounds_um)


def check_pixels_and_spectrum(edges: np.ndarray, lam: np.ndarray, weight: np.ndarray, n_rays: int,
                              n_batches: int) -> None:
    """The checks every tracer makes of its pixel edges (µm), spectrum table and ray counts."""
    if edges.ndim != 1 or edges.size < 2 or not np.all(np.diff(edges) > 0):
        raise FwdfitError("pixel_edges_um must be a strictly increasing 1-D array of >= 2 edges")
    if lam.ndim != 1 or lam.shape != weight.shape or lam.size < 2:
        raise FwdfitError("the spectrum needs at least two rows of (lambda_A, weight)")
    if not (np.all(np.isfinite(lam)) and np.all(np.isfinite(weight))):
        raise FwdfitError("the spectrum holds NaN or infinite values")
    if lam[0] <= 0 or np.any(np.diff(lam) <= 0) or np.any(weight < 0) or not np.any(weight > 0):
        raise FwdfitError("spectrum lambda_A must be positive and increasing, weights >= 0, not all 0")
    if n_batches < 2 or n_rays < n_batches:
        raise FwdfitError("need n_batches >= 2 and n_rays >= n_batches")


def _validate(layers, depth_mm, aperture, aperture_mm, aperture_distance_m, distance_mm,
              lam, weight, edges, psf_fwhm_um, n_rays, n_batches):
    """Raise FwdfitError (a ValueError) with a one-line message for nonsense input."""
    if len(layers) == 0:
        raise FwdfitError("the reference tracer needs at least one layer")
    thick = [layer.thickness_um for layer in layers]
    if not (all(t >= 0 for t in thick) and sum(thick) > 0):
        raise FwdfitError("layer thicknesses must be >= 0 with a positive total")
    if aperture not in ("square", "circular"):
        raise FwdfitError(f"unknown aperture {aperture!r} (use 'square' or 'circular')")
    if not (depth_mm > 0 and aperture_mm > 0 and psf_fwhm_um >= 0):
        raise FwdfitError("depth_mm and aperture_mm must be positive, psf_fwhm_um >= 0")
    if not aperture_distance_m * 1e3 > distance_mm:
        raise FwdfitError("aperture_distance_m must exceed the sample-to-detector distance")
    check_pixels_and_spectrum(edges, lam, weight, n_rays, n_batches)


def _sample_spectrum(rng: np.random.Generator, lam: np.ndarray, weight: np.ndarray, n: int):
    """Draw n wavelengths (Å) from the piecewise-linear density through (lam, weight), exactly."""
    width = np.diff(lam)
    cum = np.concatenate(([0.0], np.cumsum(0.5 * (weight[:-1] + weight[1:]) * width)))
    target = rng.random(n) * cum[-1]
    i = np.clip(np.searchsorted(cum, target, side="right") - 1, 0, width.size - 1)
    c, b = target - cum[i], weight[i]
    a = (weight[i + 1] - b) / (2.0 * width[i])  # mass in [0, s] is b*s + a*s^2 = c
    den = b + np.sqrt(np.maximum(b * b + 4.0 * a * c, 0.0))
    s = np.divide(2.0 * c, den, out=np.zeros(n), where=den > 0)
    return lam[i] + np.minimum(s, width[i])


def _sample_aperture(rng: np.random.Generator, aperture: str, d_um: float, n: int):
    """Aperture x (µm): uniform for 'square', x-marginal of a uniform disk for 'circular'."""
    if aperture == "square":
        return d_um * (rng.random(n) - 0.5)
    return 0.5 * d_um * np.sqrt(rng.random(n)) * np.cos(2.0 * np.pi * rng.random(n))


def _trace(stack: _Stack, u, w, a, b, lam, mu_table, r_to, side, rng, rng_rough):
    """Trace rays sitting on the stack's outer surface, about to enter layer ``r_to``.

    ``mu_table``: (n, K+1) tabulated attenuation per ray and medium (1/µm). ``side`` marks a face normal to u (else normal to w); ``rng`` draws Fresnel reflections (None:
    no partial reflection); ``rng_rough`` the normal tilts of rough faces. Returns the exit state (u, w, a, b, weight), each (n,), with weight 0 for
    rays dropped at the event cap, and the number dropped.

    A rough face's normal is tilted at every crossing by a Gaussian slope of its RMS; a ray that
    meets the tilted facet from behind passes straight, and one that the facet sends back towards
    the face finishes the depth in the medium it is in (one facet event per crossing, as the model).
    """
    bounds, h, vac = stack.bounds_um, stack.half_depth_um, len(stack.bounds_um) - 1
    out = np.zeros((5, u.size))
    idx, wt, lam2 = np.arange(u.size), np.ones(u.size), lam * lam
    r_from = np.full(u.size, vac)
    coast = np.zeros(u.size, bool)
    for _ in range(_MAX_EVENTS):
        # Cross the face from r_from to r_to: vector Snell's law with q = n^2 = 1 - λ²·SLD/π.
        face = np.where(r_from == vac, np.where(a > 0, 0, vac), np.where(a > 0, r_from + 1, r_from))
        sigma = np.where(side, stack.slope_rms_rad[face], 0.0)
        tilt = rng_rough.normal(0.0, 1.0, u.size) * sigma if np.any(sigma > 0) else np.zeros(u.size)
        cos_s, sin_s = np.cos(tilt), np.sin(tilt)
        a0, b0 = a, b
        a, b = a0 * cos_s + b0 * sin_s, b0 * cos_s - a0 * sin_s  # the facet's frame
        behind = side & (np.sign(a) != np.sign(a0))
        vn, vt = np.where(side, a, b), np.where(side, b, a)
        sld_from, sld_to = stack.sld_over_pi[r_from], stack.sld_over_pi[r_to]
        q_from, q_to = 1.0 - lam2 * sld_from, 1.0 - lam2 * sld_to
        cos2 = vn * vn + vt * vt * lam2 * (sld_from - sld_to) / q_to  # cos² of the refracted angle
        go = cos2 > 0.0
        cos_t = np.sqrt(np.where(go, cos2, 0.0))
        if rng is not None:
            k1, k2 = np.sqrt(q_from) * np.abs(vn), np.sqrt(q_to) * cos_t
            go &= rng.random(u.size) >= ((k1 - k2) / (k1 + k2)) ** 2
        go |= behind
        vt = np.where(go & ~behind, vt * np.sqrt(q_from / q_to), vt)
        vn = np.where(go & ~behind, np.copysign(cos_t, vn), np.where(behind, vn, -vn))
        a, b = np.where(side, vn, vt), np.where(side, vt, vn)
        a, b = a * cos_s - b * sin_s, b * cos_s + a * sin_s  # back from the facet's frame
        k = np.where(go, r_to, r_from)
        back = (sigma > 0) & (k != vac) & np.where(face == k, a < 0, a > 0)  # towards the face again
        coast = np.where(sigma > 0, back, coast)
        gone = k == vac
        out[:, idx[gone]] = np.stack((u, w, a, b, wt))[:, gone]
        keep = ~gone
        idx, u, w, a, b, wt, lam, lam2, k, mu_table, coast = (
            x[keep] for x in (idx, u, w, a, b, wt, lam, lam2, k, mu_table, coast))
        if idx.size == 0:
            break
        # Move to the next face of layer k, attenuating along the way.
        with np.errstate(divide="ignore", invalid="ignore"):
            su = np.where(a > 0, (bounds[k + 1] - u) / a, np.where(a < 0, (bounds[k] - u) / a, np.inf))
            sw = np.where(b > 0, (h - w) / b, np.where(b < 0, (-h - w) / b, np.inf))
        su = np.where(coast, np.inf, su)
        side = su < sw
        s = np.maximum(np.minimum(su, sw), 0.0)
        mu = stack.mu0_per_um[k] + stack.mu1_per_um_per_A[k] * lam + mu_table[np.arange(k.size), k]
        wt = wt * np.exp(-mu * s)
        u = np.where(side, np.where(a > 0, bounds[k + 1], bounds[k]), u + s * a)
        w = np.where(side, w + s * b, np.where(b > 0, h, -h))
        nb = k + np.where(a > 0, 1, -1)
        r_from, r_to = k, np.where(side & (nb >= 0) & (nb < vac), nb, vac)
    return out, idx.size


def _land(stack, geometry, x_aim, x0, ex, ez, lam, mu_table, rng, rng_rough):
    """Detector x (µm) and weight of rays along (x0, z0) + t (ex, ez) aimed at x_aim, through the sample."""
    cos_p, sin_p, centre, z0, delta = geometry
    u0, w0 = (x0 - centre) * cos_p - z0 * sin_p, (x0 - centre) * sin_p + z0 * cos_p
    a, b = ex * cos_p - ez * sin_p, ex * sin_p + ez * cos_p
    lo, hi, h = stack.bounds_um[0], stack.bounds_um[-1], stack.half_depth_um
    with np.errstate(divide="ignore", invalid="ignore"):
        tu1, tu2 = (lo - u0) / a, (hi - u0) / a
        tw1, tw2 = (-h - w0) / b, (h - w0) / b
    tu_in, tw_in = np.minimum(tu1, tu2), np.minimum(tw1, tw2)
    t_in = np.maximum(tu_in, tw_in)
    hit = np.flatnonzero(t_in < np.minimum(np.maximum(tu1, tu2), np.maximum(tw1, tw2)))
    x_det, weight = x_aim.copy(), np.ones(x0.size)  # rays that miss: straight, weight 1
    if hit.size == 0:
        return x_det, weight, 0
    a, b, t = a[hit], b[hit], t_in[hit]
    side = tu_in[hit] > tw_in[hit]  # entering through a side face
    u = np.where(side, np.where(a > 0, lo, hi), u0[hit] + t * a)
    w = np.where(side, w0[hit] + t * b, np.where(b > 0, -h, h))
    n_layers = stack.bounds_um.size - 1
    layer = np.clip(np.searchsorted(stack.bounds_um, u, side="right") - 1, 0, n_layers - 1)
    layer = np.where(side, np.where(a > 0, 0, n_layers - 1), layer)
    (u, w, a, b, wt), n_dropped = _trace(stack, u, w, a, b, lam[hit], mu_table[hit], layer, side, rng,
                                       rng_rough)
    x, z = centre + u * cos_p + w * sin_p, -u * sin_p + w * cos_p
    dx, dz = a * cos_p + b * sin_p, -a * sin_p + b * cos_p
    forward = dz > 0  # rays reflected back upstream never reach the detector
    x_det[hit] = np.where(forward, x + (delta - z) * dx / np.where(forward, dz, 1.0), np.inf)
    weight[hit] = np.where(forward, wt, 0.0)
    return x_det, weight, n_dropped


def trace_reference(
    layers: Sequence[ReferenceLayer], *, depth_mm: float, tilt_deg: float, centre_um: float,
    aperture: str, aperture_mm: float, aperture_distance_m: float, distance_mm: float,
    spectrum_lambda_A: np.ndarray, spectrum_weight: np.ndarray,
    pixel_edges_um: np.ndarray, psf_fwhm_um: float = 0.0, fresnel: bool = False,
    n_rays: int = 2_000_000, seed: int = 0, n_batches: int = 8, left_roughness_mrad: float = 0.0,
    graded_sublayers: int = 50,
) -> ReferenceResult:
    """Monte Carlo transmission profile of a tilted layer stack, exact 2-D geometric optics.

    Args:
        layers: the stack, left to right along x (at least one; zero-thickness layers are skipped).
        depth_mm: depth of every layer along the beam (mm).
        tilt_deg: rotation about the vertical axis through (centre, 0) (deg); positive moves the
            downstream end of each interface to larger x.
        centre_um: x of the stack's centre (µm).
        aperture: "square" (side aperture_mm) or "circular" (diameter aperture_mm).
        aperture_mm: aperture size (mm).
        aperture_distance_m: aperture-to-detector distance L (m).
        distance_mm: sample-centre-to-detector distance Delta (mm); must clear the sample.
        spectrum_lambda_A, spectrum_weight: (n_rows,) tabulated spectral density (Å, any scale),
            linear between rows, zero outside.
        pixel_edges_um: (n_pixel + 1,) strictly increasing detector pixel edges (µm).
        psf_fwhm_um: FWHM of a Gaussian detector blur (µm); 0 for none.
        fresnel: also reflect partially above the critical angle (Fresnel reflectivity).
        left_roughness_mrad: RMS normal slope of the stack's first (left) face; the others are
            the layers' ``roughness_mrad``.
        graded_sublayers: uniform sublayers a graded layer is traced as.
        n_rays: number of rays traced.
        seed: random seed.
        n_batches: batches for the error estimate (>= 2; >= 5 recommended).

    Returns:
        ReferenceResult with (n_pixel,) arrays T, T_err, T_att, T_att_err.
    """
    lam_tab = np.asarray(spectrum_lambda_A, float)
    w_tab = np.asarray(spectrum_weight, float)
    edges = np.asarray(pixel_edges_um, float)
    _validate(layers, depth_mm, aperture, aperture_mm, aperture_distance_m, distance_mm,
              lam_tab, w_tab, edges, psf_fwhm_um, n_rays, n_batches)
    rough_mrad = [left_roughness_mrad] + [layer.roughness_mrad for layer in layers]
    for i in reversed(range(len(layers))):  # a skipped layer's faces are one: its right-hand one
        if layers[i].thickness_um == 0:
            rough_mrad[i] = rough_mrad[i + 1]
    layers = [dataclasses.replace(layer, roughness_mrad=r) for layer, r in zip(layers, rough_mrad[1:])]
    layers = [sub for layer in layers if layer.thickness_um > 0 for sub in layer.sublayers(graded_sublayers)]
    thick = np.array([layer.thickness_um for layer in layers], float)
    sld = np.array([layer.sld_e6_per_A2 for layer in layers] + [0.0]) * 1e-6 / np.pi
    stack = _Stack(
        bounds_um=np.concatenate(([0.0], np.cumsum(thick))) - 0.5 * thick.sum(),
        half_depth_um=0.5e3 * depth_mm,
        sld_over_pi=sld,
        mu0_per_um=np.array([layer.mu_per_m for layer in layers] + [0.0]) * 1e-6,
        mu1_per_um_per_A=np.array([layer.mu_per_m_per_A for layer in layers] + [0.0]) * 1e-6,
        slope_rms_rad=1e-3 * np.array([rough_mrad[0]] + [layer.roughness_mrad for layer in layers]),
    )
    no_sld = dataclasses.replace(stack, sld_over_pi=np.zeros_like(sld), slope_rms_rad=0 * stack.slope_rms_rad)
    cos_p, sin_p = np.cos(np.radians(tilt_deg)), np.sin(np.radians(tilt_deg))
    z_half = 0.5 * thick.sum() * abs(sin_p) + stack.half_depth_um * abs(cos_p)
    delta, source_z = 1e3 * distance_mm, 1e3 * distance_mm - 1e6 * aperture_distance_m
    if delta <= max(z_half, stack.half_depth_um):
        raise FwdfitError("distance_mm must exceed the sample's half depth (the detector cuts the sample)")
    # Aim window: rays deflect by at most 2θc (θc: largest critical angle between any two media);
    # allow twice that (at least _MIN_DEFLECTION_RAD) over the whole lever arm, plus slack.
    theta_c = lam_tab[-1] * np.sqrt(np.ptp(sld))
    margin = max(_MIN_DEFLECTION_RAD, 4.0 * theta_c) * (delta + z_half) + _MARGIN_UM
    aim_lo, aim_hi = edges[0] - margin, edges[-1] + margin
    z0 = -z_half - 1.0  # start rays just upstream of the sample
    geometry = (cos_p, sin_p, centre_um, z0, delta)

    n_pix = edges.size - 1
    sums = np.zeros((3, n_batches * n_pix))  # sample, attenuation-only, open beam
    rng_rays, rng_fresnel, rng_rough = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))
    n_dropped = 0
    for start in range(0, n_rays, _CHUNK):
        n = min(_CHUNK, n_rays - start)
        batch = (start + np.arange(n)) % n_batches
        x_ap = _sample_aperture(rng_rays, aperture, 1e3 * aperture_mm, n)
        x_aim = aim_lo + (aim_hi - aim_lo) * rng_rays.random(n)
        lam = _sample_spectrum(rng_rays, lam_tab, w_tab, n)
        blur = rng_rays.normal(0.0, psf_fwhm_um / _FWHM_PER_SIGMA, n) if psf_fwhm_um > 0 else 0.0
        ex, ez = x_aim - x_ap, delta - source_z
        norm = np.hypot(ex, ez)
        ex, ez = ex / norm, ez / norm
        mu_table = 1e-6 * np.stack([layer.mu_table(lam) if layer.mu_table else np.zeros(n)
                                    for layer in layers] + [np.zeros(n)], axis=1)  # (n, K+1) 1/µm
        rays = (x_aim, x_aim - (delta - z0) * ex / ez, ex, ez, lam, mu_table)
        x_s, w_s, dropped = _land(stack, geometry, *rays, rng_fresnel if fresnel else None, rng_rough)
        x_a, w_a, _ = _land(no_sld, geometry, *rays, None, None)
        n_dropped += dropped
        for row, (x, wts) in enumerate(((x_s, w_s), (x_a, w_a), (x_aim, np.ones(n)))):
            pix = np.searchsorted(edges, x + blur, side="right") - 1
            ok = (pix >= 0) & (pix < n_pix)
            sums[row] += np.bincount(batch[ok] * n_pix + pix[ok], wts[ok], n_batches * n_pix)

    sums = sums.reshape(3, n_batches, n_pix)
    with np.errstate(divide="ignore", invalid="ignore"):
        total = sums[:2].sum(axis=1) / sums[2].sum(axis=0)
        err = np.std(sums[:2] / sums[2], axis=1, ddof=1) / np.sqrt(n_batches)
    return ReferenceResult(T=total[0], T_err=err[0], T_att=total[1], T_att_err=err[1],
                           n_rays=int(n_rays), n_dropped=int(n_dropped))


def trace_reference_rows(layers: Sequence[ReferenceLayer], *, centres_um: np.ndarray, x0_um: float,
                         pixel_um: float, n_pixels: int, sub: int = 8, **trace) -> ReferenceResult:
    """The exact reference for rows of an image whose stack centre moves from row to row.

    One trace on bins of ``pixel_um / sub``; row r's pixels (column c spans x0_um + c * pixel_um
    to one pixel further) are sums of ``sub`` bins with the stack moved by a whole number of
    bins, so every row is the reference at its own centre, ``centres_um`` (rows,) rounded to
    a bin. trace: the other arguments of ``trace_reference`` (not centre_um, pixel_edges_um).

    Returns a ReferenceResult with (rows, n_pixels) arrays T, T_err, T_att, T_att_err (errors
    of the pixel means; every row shares the one trace's Monte Carlo noise) and the centres
    used in ``centres_um`` (rows,).
    """
    bin_um = pixel_um / sub
    shifts = np.round(np.asarray(centres_um, float) / bin_um).astype(int)  # (rows,)
    start_um = x0_um - bin_um * shifts.max()
    n_bins = sub * n_pixels + int(shifts.max() - shifts.min())
    fine = trace_reference(layers, centre_um=0.0, pixel_edges_um=start_um + bin_um * np.arange(n_bins + 1),
                           **trace)
    # row r's pixel c starts at x0 + c p - centre_r in the traced frame (centre 0)
    index = (shifts.max() - shifts)[:, None] + np.arange(sub * n_pixels)[None, :]

    def rows(values, error=False):
        parts = values[index].reshape(len(shifts), n_pixels, sub)
        return np.sqrt(np.sum(parts ** 2, axis=2)) / sub if error else parts.mean(axis=2)

    return ReferenceResult(T=rows(fine.T), T_err=rows(fine.T_err, True), T_att=rows(fine.T_att),
                           T_att_err=rows(fine.T_att_err, True), n_rays=fine.n_rays, n_dropped=fine.n_dropped,
                           centres_um=shifts * bin_um)

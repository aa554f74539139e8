"""Exact ray tracer for concentric circles (rods and tubes) in float64 NumPy.

The independent reference for a cylinder model, written from the physics, not from any model code.
Frame: 2-D, the plane perpendicular to the cylinder axis (the axis runs along the detector's columns);
beam along +z, the axis at (centre_um, 0), detector plane at z = +Delta, aperture at z = Delta - L.
Lengths in µm, wavelengths in Å, SLD/π in Å^-2, mu in 1/µm inside.

A ray's component along an infinite cylinder's axis is untouched by every radial normal, so its
projection on this plane follows the 2-D laws with an in-plane index n² = 1 - λ²ρ/(π cos²ψ) and a
path longer by 1/cos ψ (ψ: angle to the plane); both corrections are of order ψ² (about 1e-5 for
a few mrad of vertical divergence) and are left out: the trace is 2-D.

At every circle: vector Snell's law at the radial normal with n² = q = 1 - λ²ρ/π, total (specular)
reflection, weight unchanged, where the refracted cosine would be imaginary; optionally Fresnel
partial reflection (probability |(k1 - k2)/(k1 + k2)|² of the normal wave-vector components).
Rays cross any number of shells, are reflected inside a shell and leave; attenuation
exp(-Σ mu(λ) path) along the actual path. The open beam is the same rays without the sample,
so T = 1 exactly where no ray through the sample lands.

Integration over the aperture, the spectrum and the aim point, two ways. "quadrature": equal-weight
strata of the spectrum and the aperture, one jittered node each per batch, and a grid of aim
points (denser, log-spaced, at every rim); a ray of each wavelength is traced once, along +z, and
turned to every aperture point's angle (circles are unchanged by rotations about their centre);
between neighbouring aim points the map to the detector is taken as linear, so each piece of the
aim line spreads its flux evenly over the pixels it covers (no histogram noise). "monte_carlo":
scrambled-Halton rays, a share aimed log-uniformly near the rims (importance weights keep the
estimate unbiased), histogrammed; slower to converge, but it can follow random Fresnel branches.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from .._errors import FwdfitError
from ._reference import ReferenceLayer, ReferenceResult, _sample_aperture, _sample_spectrum

_MAX_EVENTS = 200  # circle crossings and reflections per ray before it is dropped
_CHUNK = 400_000  # rays per vectorised chunk
_MIN_DEFLECTION_RAD = 0.02  # aim-window margin: smallest deflection allowed for ...
_MARGIN_UM = 50.0  # ... plus a fixed slack (µm)
_FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))
_RIM_MIN_UM = 1e-5  # closest log cell to a rim (µm): below R(1 - n) at 0.8 Å for R >= 5 µm
_RIM_CELLS = 64  # log cells per side of a rim (Monte Carlo)
_RIM_POINTS = 60  # log-spaced aim points per side of a rim (quadrature)
_POINT_UM = 1e-6  # a segment shorter than this lands whole (quadrature)


@dataclasses.dataclass(frozen=True)
class _Circles:
    """The sample in its own frame (centre at the origin): circles and the media between them.

    Region 0 is the vacuum outside, region k (1..M) lies inside circle k-1 and outside circle k
    (region M: the core, inside the last circle)."""

    radii_um: np.ndarray  # (M,) strictly decreasing
    sld_over_pi: np.ndarray  # (M+1,) SLD/π per region (Å^-2)
    mu0_per_um: np.ndarray  # (M+1,)
    mu1_per_um_per_A: np.ndarray  # (M+1,)
    layer_of_region: np.ndarray  # (M+1,) index into the shells, -1 for vacuum


class _Columns:
    """Hands out prepared uniform columns to samplers that ask an rng for ``random(n)``."""

    def __init__(self, columns):
        self._columns = iter(columns)

    def random(self, n):
        column = next(self._columns)
        assert column.size == n
        return column


_PRIMES = (2, 3, 5, 7)


def _scrambled_halton(rng: np.random.Generator, dims: int) -> list[list[np.ndarray]]:
    """One randomisation of a Halton sequence: a random permutation of the digits per base and
    digit position (enough digits for 2^53 points)."""
    return [[rng.permutation(b) for _ in range(int(53 / np.log2(b)) + 1)] for b in _PRIMES[:dims]]


def _halton(perms, rng: np.random.Generator, start: int, n: int) -> list[np.ndarray]:
    """Points start..start+n-1 of a digit-scrambled Halton sequence (``perms`` from
    ``_scrambled_halton``), jittered below the last digit used: every point is uniform on the
    cube (an unbiased batch) and the set has low discrepancy, so every pixel gets its share of
    aperture points and wavelengths (far less noise than independent draws)."""
    columns = []
    for base, digits in zip(_PRIMES, perms):
        i = np.arange(start, start + n, dtype=np.int64)
        u, scale = np.zeros(n), 1.0
        for perm in digits:
            scale /= base
            u += perm[i % base] * scale
            i //= base
            if not i.any() and scale * base < 1e-15:
                break
        columns.append(u + scale * rng.random(n))
    return columns


def _circles(shells, outer_radius_um, core, refraction) -> _Circles:
    thick = np.array([s.thickness_um for s in shells], float)
    n_circles = len(shells) if core == "filled" else len(shells) + 1
    inner = outer_radius_um - np.concatenate(([0.0], np.cumsum(thick)))[:n_circles]
    layer_of_region = np.array([-1, *range(len(shells))] + [-1] * (core == "vacuum"))
    sld = [0.0] + [s.sld_e6_per_A2 * 1e-6 / np.pi for s in shells] + [0.0] * (core == "vacuum")
    mu0 = [0.0] + [s.mu_per_m * 1e-6 for s in shells] + [0.0] * (core == "vacuum")
    mu1 = [0.0] + [s.mu_per_m_per_A * 1e-6 for s in shells] + [0.0] * (core == "vacuum")
    return _Circles(radii_um=inner, sld_over_pi=np.array(sld) * float(refraction),
                    mu0_per_um=np.array(mu0), mu1_per_um_per_A=np.array(mu1),
                    layer_of_region=layer_of_region)


def _validate(shells, outer_radius_um, core, aperture, aperture_mm, aperture_distance_m, distance_mm,
              lam, weight, edges, psf_fwhm_um, n_rays, n_batches, rim_fraction, rim_width_um):
    """Raise FwdfitError (a ValueError) with a one-line message for nonsense input."""
    if len(shells) == 0:
        raise FwdfitError("the cylinder tracer needs at least one shell")
    if core not in ("filled", "vacuum"):
        raise FwdfitError(f"unknown core {core!r} (use 'filled' for a rod or 'vacuum' for a tube)")
    if not outer_radius_um > 0:
        raise FwdfitError("outer_radius_um must be positive")
    for s in shells:
        if s.roughness_mrad or s.sld_end_e6_per_A2 is not None or s.mu_end_per_m is not None:
            raise FwdfitError("the cylinder tracer takes uniform, smooth shells (no roughness, no grading)")
    counted = shells if core == "vacuum" else shells[:-1]  # a rod's innermost shell fills to the axis
    thick = np.array([s.thickness_um for s in counted], float)
    if np.any(thick <= 0) or not thick.sum() < outer_radius_um:
        raise FwdfitError("every shell needs a positive thickness and the shells must leave a core of "
                          "positive radius (a rod's innermost shell fills to the axis)")
    if aperture not in ("square", "circular"):
        raise FwdfitError(f"unknown aperture {aperture!r} (use 'square' or 'circular')")
    if not (aperture_mm > 0 and psf_fwhm_um >= 0):
        raise FwdfitError("aperture_mm must be positive, psf_fwhm_um >= 0")
    if not 1e3 * distance_mm > outer_radius_um:
        raise FwdfitError("distance_mm must exceed the outer radius (the detector cuts the sample)")
    if not 1e6 * aperture_distance_m > 1e3 * distance_mm + outer_radius_um:
        raise FwdfitError("aperture_distance_m must exceed the sample-to-detector distance plus the radius")
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
    if not (0.0 <= rim_fraction < 1.0 and rim_width_um > 0):
        raise FwdfitError("rim_fraction must lie in [0, 1) and rim_width_um be positive")


def _aim_density(lo, hi, centre_um, radii_um, rim_fraction, rim_width_um):
    """Breakpoints (m+1,) and piecewise-constant density (m,) of the aim point (µm): uniform on
    [lo, hi], plus ``rim_fraction`` of the rays log-uniform in the distance from each rim (both
    sides, _RIM_MIN_UM to rim_width_um): the fringes come from rays that graze a circle, within
    R(1 - n) ~ 1e-4 to 1e-2 µm of it (total reflection) and up to ~100 µm (strong refraction)."""
    rims = np.concatenate([centre_um - radii_um, centre_um + radii_um])
    steps = np.geomspace(_RIM_MIN_UM, rim_width_um, _RIM_CELLS + 1)
    own = [rim + sign * steps for rim in rims for sign in (-1.0, 1.0)]  # each side's cell edges
    cuts = np.unique(np.concatenate([[lo, hi], *own]))
    mid = 0.5 * (cuts[1:] + cuts[:-1])
    density = np.where((mid > lo) & (mid < hi), (1.0 - rim_fraction) / (hi - lo), 0.0)
    mass = rim_fraction / (len(own) * _RIM_CELLS)  # every log cell of every side holds the same
    for edges in own:
        e = np.sort(edges)
        k = np.searchsorted(e, mid) - 1
        inside = (k >= 0) & (k < _RIM_CELLS)
        density[inside] += mass / np.diff(e)[k[inside]]
    return cuts, density


def _sample_aim(u, cuts, density):
    """Aim points (µm) by inverting the piecewise-constant CDF at uniforms u, and weights 1/density
    (a cell of zero density has no mass, so side="right" never picks it)."""
    cum = np.concatenate(([0.0], np.cumsum(density * np.diff(cuts))))
    cum /= cum[-1]
    i = np.clip(np.searchsorted(cum, u, side="right") - 1, 0, density.size - 1)
    x = cuts[i] + (u - cum[i]) / (cum[i + 1] - cum[i]) * (cuts[i + 1] - cuts[i])
    return np.clip(x, cuts[i], cuts[i + 1]), 1.0 / density[i]


def _trace(circles: _Circles, px, pz, dx, dz, lam, mu_table, rng):
    """Trace rays that sit on the outer circle, about to cross it inward, to their exit.

    px, pz: (n,) the entry points (µm, centre at the origin); dx, dz: (n,) unit directions;
    mu_table: (n, M+1) tabulated attenuation per ray and region (1/µm); rng draws Fresnel partial
    reflections (None: none). Returns the exit state
    (px, pz, dx, dz, weight), each (n,), weight 0 for rays dropped at the event cap, and the
    number dropped.
    """
    radii, s_pi = circles.radii_um, circles.sld_over_pi
    r2, m = radii * radii, radii.size
    out = np.zeros((5, px.size))
    idx, wt, lam2 = np.arange(px.size), np.ones(px.size), lam * lam
    region = np.zeros(px.size, int)
    circle = np.zeros(px.size, int)  # the circle each ray sits on
    for _ in range(_MAX_EVENTS):
        # Cross (or be reflected at) the circle: vector Snell's law at the outward radial normal.
        rc = radii[circle]
        nx, nz = px / rc, pz / rc
        dn = dx * nx + dz * nz
        to = np.where(region == circle, circle + 1, circle)  # inward from region k is region k+1
        s_from, s_to = s_pi[region], s_pi[to]
        q_from, q_to = 1.0 - lam2 * s_from, 1.0 - lam2 * s_to
        cos2 = dn * dn + (1.0 - dn * dn) * lam2 * (s_from - s_to) / q_to  # cos² of the refracted angle
        go = cos2 > 0.0
        if rng is not None:  # reflectivity of the normal wave-vector components k1 -> k2
            k1, k2 = np.sqrt(q_from) * np.abs(dn), np.sqrt(q_to * np.where(go, cos2, 0.0))
            go &= rng.random(dn.size) >= ((k1 - k2) / (k1 + k2)) ** 2
        ratio = np.sqrt(np.where(go, q_from / q_to, 1.0))
        dn_new = np.where(go, np.copysign(np.sqrt(np.where(go, cos2, 0.0)), dn), -dn)
        dx, dz = ratio * (dx - dn * nx) + dn_new * nx, ratio * (dz - dn * nz) + dn_new * nz
        norm = np.hypot(dx, dz)
        dx, dz, dn = dx / norm, dz / norm, dn_new / norm
        region = np.where(go, to, region)
        gone = region == 0  # outside, moving outward: convex from here on
        out[:, idx[gone]] = np.stack((px, pz, dx, dz, wt))[:, gone]
        keep = ~gone
        idx, px, pz, dx, dz, dn, wt, lam, lam2, region, circle, rc, mu_table = (
            x[keep] for x in (idx, px, pz, dx, dz, dn, wt, lam, lam2, region, circle, rc, mu_table))
        if idx.size == 0:
            break
        # Move to the next circle of the region: its inner circle if the ray reaches it, else its
        # outer one. With h2 = rc² dn² = rc² - b² (b the impact parameter, fixed along a segment),
        # the distances are written without cancellation.
        h2 = r2[circle] * dn * dn
        inner = np.minimum(region, m - 1)
        gap_in = r2[inner] - r2[circle] + h2  # r_in² - b²
        hits_in = (region < m) & (dn < 0) & (gap_in > 0)
        gap_out = r2[region - 1] - r2[circle] + h2  # r_out² - b²
        with np.errstate(divide="ignore", invalid="ignore"):
            s_in = (r2[circle] - r2[inner]) / (rc * np.abs(dn) + np.sqrt(np.maximum(gap_in, 0.0)))
            s_out = np.where(dn < 0, rc * np.abs(dn) + np.sqrt(np.maximum(gap_out, 0.0)),
                             (r2[region - 1] - r2[circle]) / (np.sqrt(np.maximum(gap_out, 0.0)) + rc * dn))
        s = np.where(hits_in, s_in, s_out)
        mu = (circles.mu0_per_um[region] + circles.mu1_per_um_per_A[region] * lam
              + mu_table[np.arange(region.size), region])
        wt = wt * np.exp(-mu * s)
        circle = np.where(hits_in, inner, region - 1)
        px, pz = px + s * dx, pz + s * dz
        scale = radii[circle] / np.hypot(px, pz)  # back onto the circle: no drift over many events
        px, pz = px * scale, pz * scale
    return out, idx.size


def _land(circles, centre_um, delta_um, x_aim, ex, ez, lam, mu_table, rng=None):
    """Detector x (µm) and weight of rays through (x_aim, 0) along (ex, ez), past the sample."""
    x_det = x_aim + delta_um * ex / ez  # rays that miss: straight, weight 1
    weight = np.ones(x_aim.size)
    r0 = circles.radii_um[0]
    b = (x_aim - centre_um) * ez  # impact parameter about the axis, signed
    hit = np.flatnonzero(np.abs(b) < r0)
    if hit.size == 0:
        return x_det, weight, 0
    x0, ex_h, ez_h = x_aim[hit] - centre_um, ex[hit], ez[hit]
    along = -x0 * ex_h - np.sqrt(r0 * r0 - b[hit] ** 2)  # entry: the line's first point on the circle
    px, pz = x0 + along * ex_h, along * ez_h
    scale = r0 / np.hypot(px, pz)
    (px, pz, dx, dz, wt), n_dropped = _trace(circles, px * scale, pz * scale, ex_h, ez_h,
                                            lam[hit], mu_table[hit], rng)
    forward = dz > 0  # rays reflected back upstream never reach the detector
    x_det[hit] = np.where(forward, centre_um + px + (delta_um - pz) * dx / np.where(forward, dz, 1.0), np.inf)
    weight[hit] = np.where(forward, wt, 0.0)
    return x_det, weight, n_dropped


def _first_edge_past(edges, x):
    """searchsorted(edges, x, side="right"), by arithmetic where the pixels are equal."""
    width = (edges[-1] - edges[0]) / (edges.size - 1)
    if np.allclose(np.diff(edges), width, rtol=1e-12, atol=0.0):
        return np.clip(np.floor((x - edges[0]) / width), -1, edges.size - 1).astype(np.int64) + 1
    return np.searchsorted(edges, x, side="right")


def _splat(x0, x1, weight, edges, out):
    """Add segments' weights, spread uniformly over [x0, x1] (µm; the detector image of a piece of
    the aim line between two neighbouring rays), into the pixels (edges) of ``out`` (n_pixel,).

    A segment inside one pixel (or shorter than _POINT_UM) lands whole; a longer one adds a
    ramp to the cumulative F(e) = Σ s (e - p)_+ with slope s = ±weight/length at its ends."""
    ok = np.isfinite(x0) & np.isfinite(x1) & (weight != 0)
    lo, hi, weight = np.minimum(x0, x1)[ok], np.maximum(x0, x1)[ok], weight[ok]
    n_pix = edges.size - 1
    i_lo, i_hi = _first_edge_past(edges, lo), _first_edge_past(edges, hi)
    point = (i_lo == i_hi) | (hi - lo < _POINT_UM)
    pix = np.where(i_lo == i_hi, i_lo, _first_edge_past(edges, 0.5 * (lo + hi)))[point] - 1
    inside = (pix >= 0) & (pix < n_pix)
    out += np.bincount(pix[inside], weight[point][inside], n_pix)
    ramp = ~point
    slope = weight[ramp] / (hi - lo)[ramp]
    ends = np.concatenate((lo[ramp], hi[ramp]))
    s = np.concatenate((slope, -slope))
    first = np.concatenate((i_lo[ramp], i_hi[ramp]))  # the first edge past each end
    slope_sum = np.cumsum(np.bincount(first, s, n_pix + 2))[: n_pix + 1]
    moment = np.cumsum(np.bincount(first, s * ends, n_pix + 2))[: n_pix + 1]
    out += np.diff(edges * slope_sum - moment)


def _canonical(circles: _Circles, b, lam, mu_table):
    """Rays travelling along +z at x = b (µm, axis at the origin), one wavelength each: their exit
    state (px, pz, dx, dz) and weight after the sample; rays that miss pass along their line."""
    r0 = circles.radii_um[0]
    hit = np.abs(b) < r0
    px, pz = b.copy(), np.zeros(b.size)
    dx, dz, wt = np.zeros(b.size), np.ones(b.size), np.ones(b.size)
    if hit.any():
        entry = -np.sqrt(r0 * r0 - b[hit] ** 2)
        (ex, ez, edx, edz, ew), dropped = _trace(circles, b[hit], entry, np.zeros(entry.size),
                                               np.ones(entry.size), lam[hit], mu_table[hit], None)
        px[hit], pz[hit], dx[hit], dz[hit], wt[hit] = ex, ez, edx, edz, ew
    else:
        dropped = 0
    return px, pz, dx, dz, wt, dropped


def _aim_grid(lo, hi, step_um, offset, radii_um, rim_width_um, n_rim):
    """Impact parameters (µm, about the axis): a uniform grid of ``step_um`` shifted by
    ``offset`` steps, plus log-spaced points on both sides of every rim (from _RIM_MIN_UM to
    rim_width_um), where the map to the detector bends most sharply."""
    grid = lo + step_um * (offset + np.arange(int(np.ceil((hi - lo) / step_um)) + 1))
    steps = np.geomspace(_RIM_MIN_UM, rim_width_um, n_rim)
    rims = np.concatenate((radii_um, -radii_um))
    near = (rims[:, None] + np.concatenate((steps, -steps))[None, :]).ravel()
    points = np.unique(np.concatenate(([lo, hi], grid, rims, near)))
    return points[(points >= lo) & (points <= hi)]


def _aperture_nodes(aperture, d_um, u):
    """Aperture x (µm) at stratified uniforms u: uniform for 'square', the x-marginal of a disk
    (inverse of its CDF (t sqrt(1 - t²) + arcsin t)/π + 1/2) for 'circular'."""
    if aperture == "square":
        return d_um * (u - 0.5)
    t = np.linspace(-1.0, 1.0, 4001)
    cdf = (t * np.sqrt(1.0 - t * t) + np.arcsin(t)) / np.pi + 0.5
    return 0.5 * d_um * np.interp(u, cdf, t)


def _quadrature(full, straight, shells, centre_um, delta, lever, aperture, d_um, lam_tab, w_tab,
                edges, psf_fwhm_um, aim_lo, aim_hi, n_wavelengths, n_aperture, aim_step_um,
                rim_width_um, n_batches, rng):
    """Deterministic tracing on stratified, jittered nodes (wavelength, aperture point, aim grid);
    each batch its own jitter. Every ray of a wavelength is traced once along +z: a circle is
    unchanged by rotations about its centre, so a ray from aperture point x_ap is that ray
    rotated by its angle ε to the axis. Between neighbouring aim points the map to the detector
    is taken as linear (``_splat``). Returns sums (3, n_batches, n_pixel) and rays dropped."""
    n_pix = edges.size - 1
    sums = np.zeros((3, n_batches, n_pix))
    dropped, n_traced = 0, 0
    for batch in range(n_batches):
        b = _aim_grid(aim_lo - centre_um, aim_hi - centre_um, aim_step_um, rng.random(), full.radii_um,
                      rim_width_um, _RIM_POINTS)
        u_lam = (np.arange(n_wavelengths) + rng.random(n_wavelengths)) / n_wavelengths
        lams = _sample_spectrum(_Columns([u_lam]), lam_tab, w_tab, n_wavelengths)
        x_ap = _aperture_nodes(aperture, d_um, (np.arange(n_aperture) + rng.random(n_aperture)) / n_aperture)
        blur = (rng.normal(0.0, psf_fwhm_um / _FWHM_PER_SIGMA, n_aperture) if psf_fwhm_um > 0
                else np.zeros(n_aperture))[:, None]
        share = 1.0 / (n_wavelengths * n_aperture)
        for lam in lams:
            lam_b = np.full(b.size, lam)
            mu_table = 1e-6 * np.stack([np.zeros(b.size)] + [
                shells[k].mu_table(lam_b) if k >= 0 and shells[k].mu_table else np.zeros(b.size)
                for k in full.layer_of_region[1:]], axis=1)
            exits = [_canonical(c, b, lam_b, mu_table) for c in (full, straight)]
            dropped += exits[0][5]
            n_traced += 2 * b.size
            # The ray through the aim point (centre + x0, 0) from (x_ap, delta - lever) has
            # tan ε = (centre + x0 - x_ap) / (lever - delta) and impact parameter b = x0 cos ε.
            t = (centre_um + b[None, :] - x_ap[:, None]) / (lever - delta)
            for _ in range(2):  # the fixed point converges by ~1e-6 per step
                t = (centre_um + b[None, :] * np.sqrt(1.0 + t * t) - x_ap[:, None]) / (lever - delta)
            cos_e = 1.0 / np.sqrt(1.0 + t * t)
            sin_e = t * cos_e
            x0 = b[None, :] / cos_e
            da = share * np.diff(x0, axis=1)
            x_open = centre_um + x0 + delta * t + blur
            # Pieces of the aim line that miss the sample land alike with and without it.
            hit = np.abs(b) < full.radii_um[0]
            hit = np.broadcast_to(hit[1:] | hit[:-1], da.shape)
            parts = (x_open[:, :-1], x_open[:, 1:], da)
            missed = np.zeros(edges.size - 1)
            _splat(*(p[~hit] for p in parts), edges, missed)
            sums[:, batch] += missed
            _splat(*(p[hit] for p in parts), edges, sums[2, batch])
            for row, (px, pz, dx, dz, wt, _) in enumerate(exits):
                qx, qz = px * cos_e + pz * sin_e, -px * sin_e + pz * cos_e
                vx, vz = dx * cos_e + dz * sin_e, -dx * sin_e + dz * cos_e
                with np.errstate(divide="ignore", invalid="ignore"):
                    x_det = np.where(vz > 0, centre_um + qx + (delta - qz) * vx / vz, np.inf) + blur
                w_seg = da * 0.5 * (wt[1:] + wt[:-1])[None, :]
                _splat(x_det[:, :-1][hit], x_det[:, 1:][hit], w_seg[hit], edges, sums[row, batch])
    return sums, dropped, n_traced


def trace_cylinder_reference(
    shells: Sequence[ReferenceLayer], *, outer_radius_um: float, core: str = "filled",
    centre_um: float = 0.0, aperture: str, aperture_mm: float, aperture_distance_m: float,
    distance_mm: float, spectrum_lambda_A: np.ndarray, spectrum_weight: np.ndarray,
    pixel_edges_um: np.ndarray, psf_fwhm_um: float = 0.0, fresnel: bool = False, refraction: bool = True,
    method: str = "quadrature", n_wavelengths: int = 16, n_aperture: int = 128, aim_step_um: float = 2.0,
    n_rays: int = 2_000_000, rim_fraction: float = 0.3, rim_width_um: float = 150.0,
    seed: int = 0, n_batches: int = 4,
) -> ReferenceResult:
    """Transmission profile of concentric cylindrical shells, exact 2-D geometric optics.

    Two ways to integrate over the aperture, the spectrum and the aim point, the same physics:
    "quadrature" (default) traces stratified, jittered nodes and spreads each piece of the aim
    line onto the pixels it maps to, almost free of noise (about 1e-4 in T for the defaults);
    "monte_carlo" draws rays (scrambled Halton) and histograms them, and alone offers Fresnel
    partial reflection (a reflection is a random branch, which the quadrature cannot follow).

    Args:
        shells: from the outside in (at least one); ``thickness_um`` radial (µm), SLD and mu(λ)
            as for blocks (``mu_table`` included; no roughness or grading). For a rod
            (core "filled") the innermost shell fills to the axis and its thickness is not used.
        outer_radius_um: radius of the outermost circle (µm).
        core: "filled" (a rod: the innermost shell is the core) or "vacuum" (a tube).
        centre_um: x of the cylinder axis (µm).
        aperture: "square" (side aperture_mm) or "circular" (diameter aperture_mm).
        aperture_mm: aperture size (mm).
        aperture_distance_m: aperture-to-detector distance L (m).
        distance_mm: axis-to-detector distance Delta (mm); must clear the sample.
        spectrum_lambda_A, spectrum_weight: (n_rows,) tabulated spectral density (Å, any scale),
            linear between rows, zero outside.
        pixel_edges_um: (n_pixel + 1,) strictly increasing detector pixel edges (µm).
        psf_fwhm_um: FWHM of a Gaussian detector blur (µm); 0 for none.
        fresnel: also reflect partially above the critical angle (Fresnel reflectivity;
            method "monte_carlo" only).
        refraction: False traces T with n = 1 too (then T equals T_att).
        method: "quadrature" or "monte_carlo".
        n_wavelengths, n_aperture: quadrature nodes per batch (equal-weight strata of the spectrum
            and the aperture, one jittered node each).
        aim_step_um: spacing of the quadrature's aim points (µm, in the plane of the axis);
            ``_RIM_POINTS`` more, log-spaced, on each side of every rim up to ``rim_width_um``.
        n_rays: Monte Carlo rays in all.
        rim_fraction: Monte Carlo share of the rays aimed log-uniformly within ``rim_width_um``
            (µm) of any circle's edge, the rest uniform over the window; weighted to stay unbiased.
        rim_width_um: see aim_step_um and rim_fraction.
        seed: random seed.
        n_batches: batches for the error estimate (>= 2; >= 5 recommended).

    Returns:
        ReferenceResult with (n_pixel,) arrays T, T_err, T_att, T_att_err; ``n_rays`` the rays
        traced (quadrature: each traced once along +z per wavelength, with and without
        refraction, then turned to all n_aperture points), ``n_dropped`` those stopped after
        _MAX_EVENTS crossings.
    """
    shells = list(shells)
    lam_tab, w_tab = np.asarray(spectrum_lambda_A, float), np.asarray(spectrum_weight, float)
    edges = np.asarray(pixel_edges_um, float)
    _validate(shells, outer_radius_um, core, aperture, aperture_mm, aperture_distance_m, distance_mm,
              lam_tab, w_tab, edges, psf_fwhm_um, n_rays, n_batches, rim_fraction, rim_width_um)
    if method not in ("quadrature", "monte_carlo"):
        raise FwdfitError(f"unknown method {method!r} (use 'quadrature' or 'monte_carlo')")
    if method == "quadrature" and fresnel:
        raise FwdfitError("Fresnel partial reflection needs method='monte_carlo'")
    if not (n_wavelengths >= 1 and n_aperture >= 1 and aim_step_um > 0):
        raise FwdfitError("need n_wavelengths >= 1, n_aperture >= 1 and aim_step_um > 0")
    full = _circles(shells, outer_radius_um, core, refraction)
    straight = _circles(shells, outer_radius_um, core, False)
    delta, lever = 1e3 * distance_mm, 1e6 * aperture_distance_m
    d_um = 1e3 * aperture_mm
    # Aim window in the axis plane: the pixels seen through the aperture's edges, widened for the
    # largest deflection (2θc per event, θc between any two media; allow twice that, at least
    # _MIN_DEFLECTION_RAD, over the lever arm Delta + R) and a fixed slack.
    theta_c = lam_tab[-1] * np.sqrt(np.ptp(full.sld_over_pi))
    margin = max(_MIN_DEFLECTION_RAD, 4.0 * theta_c) * (delta + outer_radius_um) + _MARGIN_UM
    # Rays that miss the sample must only cover the window's straight projection; the margin is
    # needed only for rays through the sample's shadow [centre - R, centre + R].
    penumbra = 0.5 * d_um * delta / lever + 3.0 * psf_fwhm_um
    proj_lo = edges[0] * (lever - delta) / lever - penumbra
    proj_hi = edges[-1] * (lever - delta) / lever + penumbra
    r0 = outer_radius_um
    aim_lo = min(proj_lo, max(centre_um - r0, proj_lo - margin))
    aim_hi = max(proj_hi, min(centre_um + r0, proj_hi + margin))
    if method == "quadrature":
        rng = np.random.default_rng(seed)
        sums, n_dropped, n_traced = _quadrature(
            full, straight, shells, centre_um, delta, lever, aperture, d_um, lam_tab, w_tab, edges,
            psf_fwhm_um, aim_lo, aim_hi, n_wavelengths, n_aperture, aim_step_um, rim_width_um, n_batches, rng)
        return _result(sums, n_traced, n_dropped)
    cuts, density = _aim_density(aim_lo, aim_hi, centre_um, full.radii_um, rim_fraction, rim_width_um)

    n_pix = edges.size - 1
    sums = np.zeros((3, n_batches, n_pix))  # sample, attenuation-only, open beam
    rng_rays, rng_blur, rng_fresnel = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))
    n_dropped = 0
    per_batch = np.diff(np.linspace(0, n_rays, n_batches + 1).astype(int))
    dims = 3 if aperture == "square" else 4
    for batch, n_batch in enumerate(per_batch):
        perms = _scrambled_halton(rng_rays, dims)
        for start in range(0, n_batch, _CHUNK):
            n = min(_CHUNK, n_batch - start)
            columns = _halton(perms, rng_rays, start, n)
            x_aim, aim_weight = _sample_aim(columns[0], cuts, density)
            lam = _sample_spectrum(_Columns(columns[1:2]), lam_tab, w_tab, n)
            x_ap = _sample_aperture(_Columns(columns[2:]), aperture, d_um, n)
            blur = rng_blur.normal(0.0, psf_fwhm_um / _FWHM_PER_SIGMA, n) if psf_fwhm_um > 0 else 0.0
            ex, ez = x_aim - x_ap, lever - delta
            norm = np.hypot(ex, ez)
            ex, ez = ex / norm, ez / norm
            mu_table = 1e-6 * np.stack([np.zeros(n)] + [shells[k].mu_table(lam) if k >= 0 and shells[k].mu_table
                                                        else np.zeros(n) for k in full.layer_of_region[1:]], axis=1)
            x_a, w_a, _ = _land(straight, centre_um, delta, x_aim, ex, ez, lam, mu_table)
            if refraction:
                x_s, w_s, dropped = _land(full, centre_um, delta, x_aim, ex, ez, lam, mu_table,
                                          rng_fresnel if fresnel else None)
                n_dropped += dropped
            else:
                x_s, w_s = x_a, w_a
            x_open = x_aim + delta * ex / ez
            for row, (x, wts) in enumerate(((x_s, w_s), (x_a, w_a), (x_open, np.ones(n)))):
                pix = np.searchsorted(edges, x + blur, side="right") - 1
                ok = (pix >= 0) & (pix < n_pix)
                sums[row, batch] += np.bincount(pix[ok], (wts * aim_weight)[ok], n_pix)

    return _result(sums, n_rays, n_dropped)


def _result(sums, n_rays, n_dropped) -> ReferenceResult:
    """T and T_att (ratio of the batch sums to the open beam's) and their batch errors."""
    with np.errstate(divide="ignore", invalid="ignore"):
        total = sums[:2].sum(axis=1) / sums[2].sum(axis=0)
        err = np.std(sums[:2] / sums[2], axis=1, ddof=1) / np.sqrt(sums.shape[1])
    return ReferenceResult(T=total[0], T_err=err[0], T_att=total[1], T_att_err=err[1],
                           n_rays=int(n_rays), n_dropped=int(n_dropped))

"""Exact rays through concentric circles: deflection and optical depth per impact parameter.

A ray in the plane perpendicular to the axis, aimed at impact parameter b (µm) from it,
crosses shells k = 0 (outermost) ... S-1 (the core, inner radius 0), shell k between the
circles of radius r_k (outer) and r_{k+1}, index n_k = sqrt(1 - lambda^2 rho_k / pi).
Snell's law at every circle (radial normals) keeps the Bouguer invariant n r sin(phi) = b
along the whole ray, so in shell k it is a straight chord at distance p_k = b / n_k from
the axis. It enters shell k+1 if p_k < r_{k+1} and b < n_{k+1} r_{k+1} (else it turns in
shell k: reflected inside it, or totally reflected at circle k+1); at the outer surface
it enters if b < n_0 r_0. Its polar sweep, from infinity to the point nearest the axis,
is S = (pi/2 - arccos(b / r_0)) + sum over the shells entered of
[arccos(p_k / r_k) - arccos(p_k / r_in,k)], r_in,k = max(r_{k+1}, p_k), and its outward
deflection eps = pi - 2 S; its optical depth is 2 sum mu_k (sqrt(r_k^2 - p_k^2) -
sqrt(r_in,k^2 - p_k^2)) over the same shells. The ray is symmetric about its nearest
point, so half of it is traced.

eps comes from pi - 2 S, O(1) terms that cancel to ~1e-5: float64 is required (float32
leaves ~1e-7 rad of noise, a µm at 10 mm). Units: µm, rad, mu in 1/µm.
"""

from __future__ import annotations

import jax.numpy as jnp


def _polar(p, r):
    """arccos(p / r) where p < r, else 0 (finite with finite derivatives below the circle)."""
    inside = p < r
    ratio = jnp.where(inside, p / jnp.where(inside, r, 1.0), 0.0)
    return jnp.where(inside, jnp.arccos(ratio), 0.0)


def _half_chord(p, r):
    """sqrt(r^2 - p^2) where p < r, else 0 (the gradient 0 there, not 0 x inf)."""
    square = r * r - p * p
    inside = square > 0
    return jnp.where(inside, jnp.sqrt(jnp.where(inside, square, 1.0)), 0.0)


def _shells(b, radii, n, mu):
    """Per shell of rays at impact parameters b (B,): the polar sweep (B, S) and optical depth
    (B, S) of the ray's half in it (0 where the ray does not reach it), and whether the ray
    reaches it (B, S) bool; and the sweep outside the sample (B,). radii, n, mu: as ``trace``."""
    outer, inner = radii[:-1], radii[1:]
    p = b[:, None] / n[None, :]  # (B, S): the chord's distance from the axis in each shell
    turns = p >= inner[None, :]
    r_in = jnp.where(turns, p, inner[None, :])
    sweep = _polar(p, outer[None, :]) - _polar(p, r_in)
    length = _half_chord(p, outer[None, :]) - _half_chord(p, r_in)
    hit = b < radii[0]
    enters = b[:, None] < n[None, :] * outer[None, :]  # (B, S): across circle k into shell k
    # shell k is reached if every shell before it was crossed (entered, not turned in) and k is entered
    passes = jnp.concatenate([jnp.ones_like(turns[:, :1]), ~turns[:, :-1]], axis=1) & enters
    reached = jnp.cumprod(passes, axis=1).astype(bool) & hit[:, None]
    outside = jnp.where(hit, 0.5 * jnp.pi - _polar(b, radii[0]), 0.5 * jnp.pi)
    return outside, jnp.where(reached, sweep, 0.0), jnp.where(reached, mu[None, :] * length, 0.0), reached


def trace(b, radii, n, mu):
    """Outward deflection (rad) and optical depth of rays at impact parameters b.

    b (B,) µm >= 0; radii (S+1,) µm, decreasing, radii[S] = 0 (the core's centre); n (S,)
    refractive indices; mu (S,) 1/µm. Returns eps (B,), depth (B,).
    """
    outside, sweep, attenuation, _ = _shells(b, radii, n, mu)
    return jnp.pi - 2.0 * (outside + jnp.sum(sweep, axis=1)), 2.0 * jnp.sum(attenuation, axis=1)


def fresnel_trace(b, radii, n, mu):
    """``trace`` with Fresnel partial reflection at every circle a ray crosses, to first order:
    its branches (B, 2S + 1) of deflection (rad), optical depth and share of the ray.

    Crossing circle k (into shell k, at the same grazing angle on the way out) reflects the
    share R_k = ((q - q_k) / (q + q_k))^2, q_k = sqrt(n_k^2 - (b / r_k)^2) and q that of the
    medium outside circle k (Snell's normal wave-vector components; R_k -> 1 at the critical
    angle, where the ray's total reflection takes over). Branches: the ray reflected by no
    circle (share prod (1 - R_k)^2); reflected back out at circle k instead of entering it
    (R_k times the crossings before it); reflected once inside circle k on its way out, which
    adds a second pass through circle k (R_k times every crossing: circle k's and those outside
    it twice, those inside it four times). A reflection preserves b, so every branch lands
    as a ray does (``_model``); multiple reflections (order R^2) are left out.
    """
    outside, sweep, attenuation, reached = _shells(b, radii, n, mu)
    n_outside = jnp.concatenate([jnp.ones((1,), n.dtype), n[:-1]])
    along = b[:, None] / jnp.where(radii[:-1] > 0, radii[:-1], 1.0)[None, :]  # b / r_k, (B, S)
    normal = lambda index: jnp.sqrt(jnp.maximum(index[None, :] ** 2 - along**2, 1e-30))
    q_out, q_in = normal(n_outside), normal(n)
    R = jnp.where(reached, jnp.square((q_out - q_in) / (q_out + q_in)), 0.0)
    kept = jnp.square(1.0 - R)  # both crossings of circle k
    before = _exclusive_cumprod(kept)  # the circles outside k
    after = _exclusive_cumprod(kept[:, ::-1])[:, ::-1]  # the circles inside k
    half_sweep = outside + jnp.sum(sweep, axis=1)
    half_depth = jnp.sum(attenuation, axis=1)
    inner_sweep = jnp.cumsum(sweep[:, ::-1], axis=1)[:, ::-1]  # from circle k to the nearest point
    inner_depth = jnp.cumsum(attenuation[:, ::-1], axis=1)[:, ::-1]
    outer_sweep = outside[:, None] + jnp.cumsum(sweep, axis=1) - sweep  # to circle k
    outer_depth = jnp.cumsum(attenuation, axis=1) - attenuation
    eps = jnp.concatenate([(jnp.pi - 2.0 * half_sweep)[:, None], jnp.pi - 2.0 * outer_sweep,
                           jnp.pi - 2.0 * (half_sweep[:, None] + inner_sweep)], axis=1)
    depth = 2.0 * jnp.concatenate([half_depth[:, None], outer_depth, half_depth[:, None] + inner_depth], axis=1)
    share = jnp.concatenate([(before[:, -1] * kept[:, -1])[:, None], before * R,
                             before * kept * R * after * after], axis=1)
    return eps, depth, share


def _exclusive_cumprod(x):
    """Products along axis 1 of the entries before each one (1 for the first)."""
    return jnp.cumprod(jnp.concatenate([jnp.ones_like(x[:, :1]), x[:, :-1]], axis=1), axis=1)


def chords(b, radii):
    """Straight chords (B, S) µm of rays at impact parameters b (B,) through each shell: the
    attenuation-only path (n = 1 everywhere)."""
    outer, inner = radii[None, :-1], radii[None, 1:]
    b = b[:, None]
    return 2.0 * (_half_chord(b, outer) - _half_chord(b, inner))

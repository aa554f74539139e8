"""Refraction at one interface as a deflection kernel: cumulative intensity at pixel edges.

Only rays that cross an interface inside the sample are refracted, and only rays
within ``depth * |a|`` of it (a: grazing angle) cross it. For one interface and
one crossing direction this module integrates those rays exactly over angle
(the aperture's angular distribution has closed-form antiderivatives) and
returns, at each detector edge E, the intensity (µm of open beam) that lands left
of E. The crossing depth z and the wavelength are summed by quadrature outside; the
``*_kinks`` functions give the grazing angles at which each cumulative kinks as a
function of z, where that quadrature is split.

Frame: the "local" frame in which rays cross from medium 1 (left) into medium 2
(right), i.e. grazing angle a > 0; the other direction is the mirror image.
Paraxial optics: angles are slopes (|angle| < 0.05 rad). Lengths in µm.

Snell at a grazing angle: a2^2 = a^2 - k with k = 2 (delta_2 - delta_1). For
k > 0 rays with a^2 < k are totally reflected (a2 = -a).
"""

from __future__ import annotations

import jax.numpy as jnp

from ._aperture import APERTURES

_TINY = 1e-30


def _safe_sqrt(x):
    """sqrt with a finite gradient at 0 (the clip that follows zeroes it there)."""
    return jnp.sqrt(jnp.maximum(x, _TINY))


class AngularMass:
    """Rays through a point (x, z) per unit crossing length: int q(theta) * a da.

    The aperture (width ``aperture_um``) is seen from a crossing point at lateral
    position ``position_um``, ``source_um`` downstream of the aperture; ``slope`` is
    the interface's slope. Arrays broadcast together.
    """

    def __init__(self, aperture: str, position_um, slope, source_um, aperture_um: float):
        self._cdf, self._moment, _ = APERTURES[aperture]
        to_source = 1.0 / source_um
        self.half_width = 0.5 * aperture_um * to_source  # rad, the angle it subtends / 2
        self.inverse_half_width = (2.0 / aperture_um) * source_um
        self.offset = position_um * to_source - slope  # grazing angle of the aperture centre
        lo, hi = self.offset - self.half_width, self.offset + self.half_width
        self.a_min, self.a_max = jnp.maximum(lo, 0.0), jnp.maximum(hi, 0.0)

    def primitive(self, a):
        """int_{a_lo}^{a} q(slope + t) t dt for a already clipped to the positive range."""
        v = (a - self.offset) * self.inverse_half_width
        return self.offset * self._cdf(v) + self.half_width * self._moment(v)

    def between(self, a_low, a_high):
        return self.primitive(a_high) - self.primitive(a_low)


def straight_cumulative(mass: AngularMass, grazing_at_edge):
    """Undeflected crossing rays landing left of each edge.

    grazing_at_edge: (E - c) / (Delta - z), the grazing angle that reaches edge E.
    """
    a = jnp.clip(grazing_at_edge, mass.a_min, mass.a_max)
    return mass.between(mass.a_min, a)


def _critical(mass: AngularMass, k):
    """Grazing angle below which rays are totally reflected, clipped to the crossing range."""
    return jnp.clip(_safe_sqrt(k) * (k > 0), mass.a_min, mass.a_max)


def deflected_cumulative(mass: AngularMass, grazing_at_edge, k):
    """Refracted plus totally reflected crossing rays landing left of each edge.

    k = 2 (delta_2 - delta_1) (dimensionless, broadcastable); refracted rays leave
    at a2 = sqrt(a^2 - k) > 0, reflected ones at -a.
    Returns (refracted, reflected) cumulative masses.
    """
    critical = _critical(mass, k)
    positive = jnp.maximum(grazing_at_edge, 0.0)
    incoming = _safe_sqrt(positive * positive + k)
    refracted = mass.between(critical, jnp.clip(incoming, critical, mass.a_max))
    reflected_from = jnp.clip(-grazing_at_edge, mass.a_min, critical)
    reflected = mass.between(reflected_from, critical)
    return refracted, reflected


# Kinks: the grazing angles at an edge at which a cumulative's clips switch. At a fixed
# edge they move with the crossing depth, and the depth quadrature is split there.


def straight_kinks(mass: AngularMass):
    """Grazing angles at the edge where ``straight_cumulative`` has kinks: the fan's ends."""
    return mass.a_min, mass.a_max


def deflected_kinks(mass: AngularMass, k, right_of_interface):
    """Grazing angles at the edge where ``deflected_cumulative`` has kinks.

    Right of the interface's projection (grazing > 0) only the refracted rays land,
    from the critical angle (where it is above sqrt(k)) and from the fan's end; left
    of it only the reflected ones, from the fan's start and the critical angle.
    """
    critical = _critical(mass, k)
    refracted = (_safe_sqrt(critical * critical - k) * (critical * critical > k),
                 _safe_sqrt(mass.a_max * mass.a_max - k) * (mass.a_max * mass.a_max > k))
    reflected = (-mass.a_min, -critical)
    return tuple(jnp.where(right_of_interface, a, b) for a, b in zip(refracted, reflected))


def landing_range(offset, half_width, k, xp=jnp):
    """Outgoing grazing angles (lo, hi) (rad) of every ray that crosses the interface.

    offset, half_width: as in ``AngularMass`` (the crossing rays have grazing angles
    a in [max(offset - half_width, 0), max(offset + half_width, 0)]); k: the value
    of largest |k| over the spectrum (k ~ lambda^2 keeps its sign). Straight,
    refracted and reflected rays all leave at angles in [lo, hi]: such a ray lands
    at (angle * lever) from the interface's projection. xp: the array module (``jax.numpy`` in
    the model, ``numpy`` for the static plan, which must not dispatch JAX operations).
    """
    a_min = xp.maximum(offset - half_width, 0.0)
    a_max = xp.maximum(offset + half_width, 0.0)
    root = xp.sqrt(xp.abs(k))
    reflected = -xp.minimum(a_max, root)  # the steepest totally reflected ray
    refracted = xp.sqrt(xp.maximum(a_min * a_min - k, 0.0))
    lo = xp.where(k > 0, xp.where(a_min < root, reflected, refracted), a_min)
    hi = xp.where(k > 0, a_max, xp.sqrt(a_max * a_max - xp.minimum(k, 0.0)))
    return lo, hi

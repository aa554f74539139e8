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
k > 0 rays with a^2 < k are totally reflected (a2 = -a). With Fresnel partial
reflection (``fresnel_transfer``) the other rays are reflected with probability
R = ((a - a2) / (a + a2))^2, for either sign of k.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ._aperture import APERTURES

_TINY = 1e-30
_NO_CONTRAST = 1e-12  # |k| below this reflects as this (a transfer of ~1e-13 of the beam)


def _clip(x, lo, hi):
    """``jnp.clip(x, lo, hi)`` whose derivative stays right where lo == hi.

    The clips here often have bounds that coincide for a whole configuration (the critical
    angle clipped to a fan that lies below it is the fan's end, and that end clips the next
    angle from both sides). jnp.clip's derivative then rests on ties between equal values, and
    XLA may recompute one of them elsewhere with a fused multiply-add, one unit in the last
    place off: the tie is lost and so is the derivative (jitted reverse-mode gradients of a
    Fresnel model were 26 % off in the tilt). Clipping x - lo to [0, hi - lo] instead makes
    every outcome of such a tie the derivative of lo or of hi, which are then equal."""
    return lo + jnp.clip(x - lo, 0.0, hi - lo)


def _safe_sqrt(x):
    """sqrt with a finite gradient at 0 (the clip that follows zeroes it there)."""
    return jnp.sqrt(jnp.maximum(x, _TINY))


def in_plane_frame(boundary_um, slope, z_mid_um, distance_um, plane_um):
    """A face's geometry (boundary at z = 0, z-centre, distance to the detector, µm) in the
    frame whose z = 0 is the depth ``plane_um`` at which the step profile assigns its rays
    (``_model._assignment_planes``): the kernels subtract that assignment at their z = 0."""
    return boundary_um + slope * plane_um, z_mid_um - plane_um, distance_um - plane_um


class AngularMass:
    """Rays through a point (x, z) per unit crossing length: int q(theta) * a da.

    The aperture (width ``aperture_um``) is seen from a crossing point at lateral
    position ``position_um``, ``source_um`` downstream of the aperture; ``slope`` is
    the interface's slope. Arrays broadcast together.

    tilt (rad, optional): a rough face's local normal is tilted by ``tilt``; the grazing
    angles are then local ones, a' = a - tilt, of the rays that cross the face (a > 0)
    and meet the facet from the front (a' > 0), each counted with its true (global)
    crossing rate a. The rays that meet it from behind (0 < a <= tilt) pass straight
    (``behind``).
    """

    def __init__(self, aperture: str, position_um, slope, source_um, aperture_um: float, tilt=None,
                 floor=None, ceiling=None):
        self._cdf, self._moment, _ = APERTURES[aperture]
        self.square = aperture == "square"  # the mass is then quadratic in the angle (``fresnel_transfer``)
        to_source = 1.0 / source_um
        self.half_width = 0.5 * aperture_um * to_source  # rad, the angle it subtends / 2
        self.inverse_half_width = (2.0 / aperture_um) * source_um
        self.offset = position_um * to_source - slope  # grazing angle of the aperture centre
        self.tilt = tilt
        crossing = 0.0
        if tilt is not None:
            self.offset = self.offset - tilt
            crossing = jnp.maximum(-tilt, 0.0)
        lo, hi = self.offset - self.half_width, self.offset + self.half_width
        self.a_min, self.a_max = jnp.maximum(lo, crossing), jnp.maximum(hi, crossing)
        if floor is not None:  # only the rays above ``floor`` (rad), e.g. those that reach a second face
            self.a_min = _clip(floor, self.a_min, self.a_max)
        if ceiling is not None:  # only the rays below ``ceiling`` (rad)
            self.a_max = _clip(ceiling, self.a_min, self.a_max)

    def primitive(self, a):
        """int_{a_lo}^{a} q(slope + t) (t + tilt) dt for a already clipped to the crossing range."""
        v = (a - self.offset) * self.inverse_half_width
        weight = self.offset if self.tilt is None else self.offset + self.tilt
        return weight * self._cdf(v) + self.half_width * self._moment(v)

    def behind(self, grazing_at_edge):
        """Rays of a rough face that meet its facet from behind (0 < a <= tilt), undeflected,
        landing left of each edge (global grazing angle ``grazing_at_edge``)."""
        low = jnp.maximum(self.offset + self.tilt - self.half_width, 0.0)
        high = jnp.maximum(jnp.minimum(self.offset + self.tilt + self.half_width, self.tilt), low)
        a = _clip(grazing_at_edge, low, high)
        return self.primitive(a - self.tilt) - self.primitive(low - self.tilt)

    def cdf(self, a):
        """Fraction of the aperture's rays below grazing angle a."""
        return self._cdf((a - self.offset) * self.inverse_half_width)

    def between(self, a_low, a_high):
        return self.primitive(a_high) - self.primitive(a_low)


def straight_cumulative(mass: AngularMass, grazing_at_edge):
    """Undeflected crossing rays landing left of each edge.

    grazing_at_edge: (E - c) / (Delta - z), the grazing angle that reaches edge E.
    """
    a = _clip(grazing_at_edge, mass.a_min, mass.a_max)
    return mass.between(mass.a_min, a)


def _critical(mass: AngularMass, k):
    """Grazing angle below which rays are totally reflected, clipped to the crossing range."""
    return _clip(_safe_sqrt(k) * (k > 0), mass.a_min, mass.a_max)


def deflected_cumulative(mass: AngularMass, grazing_at_edge, k, reflect_k=None, floor=None, side=None):
    """Refracted plus totally reflected crossing rays landing left of each edge.

    k = 2 (delta_2 - delta_1) (dimensionless, broadcastable); refracted rays leave
    at a2 = sqrt(a^2 - k) > 0, reflected ones at -a. reflect_k: rays with a^2 below
    it are reflected (default k; larger where a face behind a thin layer reflects them).
    floor: only rays above this angle (those below are a thin layer's guided rays).
    Returns (refracted, reflected) cumulative masses; with ``side`` (bool, broadcastable) one
    of them per edge, the refracted where side is True.
    """
    a_min = mass.a_min if floor is None else _clip(floor, mass.a_min, mass.a_max)
    reflect_k = k if reflect_k is None else reflect_k
    critical = _clip(_safe_sqrt(reflect_k) * (reflect_k > 0), a_min, mass.a_max)
    positive = jnp.maximum(grazing_at_edge, 0.0)
    incoming = _safe_sqrt(positive * positive + k)
    refracted = (critical, _clip(incoming, critical, mass.a_max))
    reflected = (_clip(-grazing_at_edge, a_min, critical), critical)
    return _between_by_side(mass.between, refracted, reflected, side)


def _between_by_side(between, first, second, side):
    """between(*first), between(*second); with ``side`` one call, first where side is True."""
    if side is None:
        return between(*first), between(*second)
    return between(*(jnp.where(side, a, b) for a, b in zip(first, second)))


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
    return _sided_kinks(_refracted_kinks(mass, k, critical), (-mass.a_min, -critical), right_of_interface)


def fresnel_kinks(mass: AngularMass, k, right_of_interface):
    """Grazing angles at the edge where ``fresnel_transfer`` has kinks.

    As ``deflected_kinks`` right of the interface's projection; left of it the
    partially reflected rays land, from the critical angle and the fan's end.
    """
    critical = _critical(mass, k)
    return _sided_kinks(_refracted_kinks(mass, k, critical), (-critical, -mass.a_max), right_of_interface)


def deflected_and_fresnel_kinks(mass: AngularMass, k, right_of_interface):
    """Grazing angles at the edge where ``deflected_cumulative`` or ``fresnel_transfer`` has
    kinks, three, for one set of depth nodes for both: right of the interface's projection the
    two of ``deflected_kinks`` and one between them (a cut that only shortens a smooth piece),
    left of it the fan's start and end and the critical angle."""
    critical = _critical(mass, k)
    refracted = _refracted_kinks(mass, k, critical)
    return _sided_kinks(refracted + (0.5 * (refracted[0] + refracted[1]),), (-mass.a_min, -critical, -mass.a_max),
                        right_of_interface)


def _refracted_kinks(mass: AngularMass, k, critical):
    """Outgoing angles of the refracted rays from the critical angle and from the fan's end."""
    return (_safe_sqrt(critical * critical - k) * (critical * critical > k),
            _safe_sqrt(mass.a_max * mass.a_max - k) * (mass.a_max * mass.a_max > k))


def _sided_kinks(right, left, right_of_interface):
    return tuple(jnp.where(right_of_interface, a, b) for a, b in zip(right, left))


def fresnel_transfer(mass: AngularMass, grazing_at_edge, k, nodes, weights, returning=None, side=None):
    """Crossing rays that Fresnel reflection moves from the refracted to the reflected beam.

    Of the rays above the critical angle (every ray for k <= 0) a fraction R(a) =
    ((a - a2) / (a + a2))^2 is reflected (leaves at -a) instead of refracted. Returns
    (loss, gain): the refracted rays landing left of each edge that are lost, and the
    reflected rays that land there, both as masses like ``deflected_cumulative``.
    returning = (turn, beyond, leaves, below), for the second face of a thin layer: reflected
    rays above ``turn`` go back through the layer; the share ``leaves(a)`` of them leaves it
    through its first face (those above ``beyond`` land left of the edge), the rest is reflected
    there too and leaves the back inside the layer (those below ``below`` land left of the
    edge). Returns (loss, gain, returned) then, gain those below ``turn`` and the latter.
    side (bool, broadcastable; not with ``returning``): one of (loss, gain) per edge, the loss where
    side is True.

    With v = |k| / (a + a2)^2 (v in (0, 1], 1 at the critical angle, or at a = 0 for
    k < 0) R = v^2 and a(v) = sqrt|k| (v^-1/2 + sign(k) v^1/2) / 2, so that, after an
    integration by parts against the mass M(a), int R dM = [R M] + int 2 v M(a(v)) dv:
    smooth in v through the critical angle, and with a (.)^(3/2) end point at the circle's rim.
    nodes, weights: Gauss-Legendre on [0, 1] (static tuples). For the square aperture, whose
    mass is quadratic in a, the integral is in closed form (``_square_reflected_mass``) where
    no ``share`` weighs it.
    """
    k = jnp.where(jnp.abs(k) < _NO_CONTRAST, _NO_CONTRAST, k)  # a negligible transfer, finite in float32
    critical = _critical(mass, k)
    incoming = _safe_sqrt(jnp.maximum(grazing_at_edge, 0.0) ** 2 + k)
    lost_up_to = _clip(incoming, critical, mass.a_max)
    gained_from = _clip(-grazing_at_edge, critical, mass.a_max)
    root = jnp.sqrt(jnp.abs(k))

    def v_at(a):  # at most 1, also where no ray is above the critical angle (a = a_max < sqrt(k))
        return jnp.abs(k) / jnp.maximum(jnp.square(a + _safe_sqrt(a * a - k)), jnp.abs(k))

    def reflected_mass(a_low, a_high, share=None):  # int_{a_low}^{a_high} R share dM, a_low <= a_high
        a_low, a_high = jnp.broadcast_arrays(a_low, a_high)
        v_low, v_high = v_at(a_low), v_at(a_high)  # v_high <= v_low
        if share is None and mass.square:
            return _square_reflected_mass(mass, k, root, v_low, v_high)

        def angle(v):
            s = jnp.sqrt(v)
            return _clip(0.5 * (root / s + (k / root) * s), a_low, a_high)

        def weight(v):  # R, times the share of those rays (a function of a) where given
            return v * v * share(angle(v))

        base = mass.primitive(a_low)
        along = np.asarray(nodes).reshape((-1,) + (1,) * v_low.ndim)  # a leading node axis
        v = v_high + (v_low - v_high) * along
        if share is None:  # d R / dv = 2 v
            slope, at_high = 2.0 * v, v_high**2
        else:
            slope, at_high = jax.jvp(weight, (v,), (jnp.ones_like(v),))[1], weight(v_high)
        integral = jnp.tensordot(np.asarray(weights), slope * (mass.primitive(angle(v)) - base), 1)
        return at_high * (mass.primitive(a_high) - base) + (v_low - v_high) * integral

    if returning is None:
        return _between_by_side(reflected_mass, (critical, lost_up_to), (gained_from, mass.a_max), side)
    turn, beyond, leaves, below = returning
    turn = _clip(turn, critical, mass.a_max)
    stays = lambda a: 1.0 - leaves(a)
    gained = (reflected_mass(jnp.minimum(gained_from, turn), turn)
              + reflected_mass(turn, _clip(below, turn, mass.a_max), stays))
    return (reflected_mass(critical, lost_up_to), gained,
            reflected_mass(_clip(beyond, turn, mass.a_max), mass.a_max, leaves))


def _square_reflected_mass(mass: AngularMass, k, root, v_low, v_high):
    """int R dM from v_low down to v_high (``fresnel_transfer``'s v) in closed form for the square
    aperture, whose mass is dM = (a + tilt) da / (2 half-width) inside the fan: with
    a(v) = root (v^-1/2 + sign(k) v^1/2) / 2, a da = |k| (1 - v^-2) dv / 8 and
    da = root (sign(k) v^-1/2 - v^-3/2) dv / 4, so that int v^2 a da = |k| [v^3 / 3 - v] / 8
    and int v^2 da = root [2 sign(k) v^5/2 / 5 - 2 v^3/2 / 3] / 4."""
    cubic = lambda v: v * (v * v / 3.0 - 1.0)
    integral = jnp.abs(k) / 8.0 * (cubic(v_high) - cubic(v_low))
    if mass.tilt is not None:  # a rough face: rays cross at the global angle a + tilt
        sign = jnp.sign(k)
        half_powers = lambda v: v * jnp.sqrt(v) * (0.4 * sign * v - 2.0 / 3.0)
        integral = integral + mass.tilt * root / 4.0 * (half_powers(v_high) - half_powers(v_low))
    return 0.5 * mass.inverse_half_width * integral


def landing_range(offset, half_width, k, fresnel: bool, xp=jnp, tilt=None):
    """Outgoing grazing angles (lo, hi) (rad) of every ray that crosses the interface.

    offset, half_width: as in ``AngularMass`` (the crossing rays have grazing angles
    a in [max(offset - half_width, 0), max(offset + half_width, 0)]); k: the value
    of largest |k| over the spectrum (k ~ lambda^2 keeps its sign). Straight,
    refracted and reflected rays all leave at angles in [lo, hi]: such a ray lands
    at (angle * lever) from the interface's projection. fresnel: whether every
    crossing ray may be reflected (where there is contrast). xp: the array module
    (``jax.numpy`` in the model, ``numpy`` for the static plan, which must not
    dispatch JAX operations). tilt (rad, optional): a rough face whose normal tilts by up
    to this much either way (``_rough_landing_range``).
    """
    a_min = xp.maximum(offset - half_width, 0.0)
    a_max = xp.maximum(offset + half_width, 0.0)
    root = xp.sqrt(xp.abs(k))
    if tilt is not None:
        return _rough_landing_range(a_min, a_max, k, root, fresnel, tilt, xp)
    reflected = -xp.minimum(a_max, root)  # the steepest totally reflected ray
    refracted = xp.sqrt(xp.maximum(a_min * a_min - k, 0.0))
    lo = xp.where(k > 0, xp.where(a_min < root, reflected, refracted), a_min)
    hi = xp.where(k > 0, a_max, xp.sqrt(a_max * a_max - xp.minimum(k, 0.0)))
    if fresnel:
        lo = xp.where(k != 0, -a_max, lo)
    return lo, hi


def landing_regions(a_min, a_max, k, tilt=0.0, xp=jnp):
    """Where the deflected rays of one wavelength and one normal tilt leave: two intervals of
    outgoing grazing angles (rad), ((lo, hi) left, (lo, hi) right of the facet's projection).

    a_min, a_max: the crossing rays' global grazing angles (``AngularMass`` without tilt); k as
    in ``deflected_cumulative``; tilt (rad): the facet's normal tilt (0: a sharp face). Left: the
    rays reflected, totally or partially (at t - a', a' = a - t), and those that meet the facet
    from behind (a <= t, straight on). Right: the refracted ones (t + sqrt(a'^2 - k)). Outside
    both every deflected cumulative is flat in the edge. The left interval is at most as wide as
    the fan (a_max - a_min), the right one at most sqrt(a'_max^2 - a'_min^2), reached for
    k = a'_min^2 (``_plan`` sizes the kernels' sub-windows with this). xp: as ``landing_range``.
    An interval that holds no ray is returned as the other one."""
    front_lo, front_hi = xp.maximum(a_min - tilt, 0.0), xp.maximum(a_max - tilt, 0.0)
    meets, behind = front_hi > front_lo, tilt > a_min  # some rays meet the facet from the front / behind
    left_lo = xp.where(meets, xp.where(behind, xp.minimum(tilt - front_hi, a_min), tilt - front_hi), a_min)
    left_hi = xp.where(meets, tilt - front_lo, xp.minimum(a_max, tilt))
    refracted_from = xp.maximum(front_lo, xp.sqrt(xp.maximum(k, 0.0)))
    refracts = front_hi > refracted_from
    right_lo = tilt + xp.sqrt(xp.maximum(refracted_from * refracted_from - k, 0.0))
    right_hi = tilt + xp.sqrt(xp.maximum(front_hi * front_hi - k, 0.0))
    left_lo, left_hi = xp.where(meets | behind, left_lo, right_lo), xp.where(meets | behind, left_hi, right_hi)
    return (left_lo, left_hi), (xp.where(refracts, right_lo, left_lo), xp.where(refracts, right_hi, left_hi))


def _rough_landing_range(a_min, a_max, k, root, fresnel: bool, tilt, xp):
    """``landing_range`` of a face whose normal tilts by t in [-tilt, tilt]: a ray at global angle
    a meets the facet at a' = a - t and leaves at t - a' = 2 t - a when reflected (a' < sqrt(k),
    or any a' > 0 with Fresnel reflection), at t + sqrt(a'^2 - k) when refracted, and at a when
    it meets the facet from behind (a' <= 0). Totally reflected rays (t > a - sqrt(k)) leave
    above max(2 t - a_max, t - sqrt(k), a - 2 sqrt(k)), partially reflected ones above
    2 t - a_max. For k > 0 a refracted ray's angle falls as t grows, to a - sqrt(k) where the ray
    meets the facet at its critical angle; for k < 0 it grows with t and never falls below a,
    nor rises above its value at t = min(tilt, a_max) from a_max. Each bound is reached by some
    ray; the window they set (``_plan._window_um``) is narrower than the sharp range widened by
    2 tilt either way by at least tilt x lever."""
    totally = xp.maximum(xp.maximum(-2.0 * tilt - a_max, -tilt - root), a_min - 2.0 * root)
    reflected = xp.where(k != 0, -2.0 * tilt - a_max, totally) if fresnel else totally
    above = xp.sqrt(xp.maximum(xp.square(a_min - tilt) - k, 0.0))  # from a_min at t = tilt, if not critical
    refracted = xp.where(a_min - root <= tilt, xp.maximum(a_min - root, -tilt), tilt + above)
    lo = xp.where(k > 0, xp.minimum(refracted, reflected), xp.minimum(a_min, reflected) if fresnel else a_min)
    steepest = xp.minimum(tilt, a_max)
    hi = xp.maximum(a_max, steepest + xp.sqrt(xp.square(a_max - steepest) + xp.maximum(-k, 0.0)))
    return lo, hi

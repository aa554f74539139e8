"""A thin layer coupled: rays that cross both of its faces inside the sample.

Independent kernels (``_model._crossing_kernel``) treat each face as if the media on
either side were semi-infinite. A layer B (width w at the mid-plane) between media A
and C is thin when rays entering it reach its other face inside the depth, i.e. when
w is below the sideways drift depth x |angle|. For such a layer the rays are split,
for each crossing direction (here A -> C, the mirror C -> A alike), into disjoint sets:

- rays from A meeting the first face at depth z that are reflected there, or refract
  into B and leave the sample's back before reaching the second face (outgoing angle
  u < w / (z_hi - z)): the first face's own kernel, restricted (``face_limits``);
  rays refracted into B that the second face reflects (u^2 < k_AC - k_AB) return into
  A at once in a thin layer and count as reflected there;
- rays that started in B (entered through the front face) and meet the second face:
  its own kernel restricted to incoming angles a < w / (z - z_lo);
- rays from A that cross both faces (``through_kernel``): they leave into C at
  a_C = sqrt(a^2 - k_AC) from the second face, w further along and w / u deeper, so
  they land at w + a_C (Delta - z - w / u); their path in B, w / u, weights them by
  exp(-(mu_B - mu_C) w / u).

Rays of B totally reflected at a face are followed to the sample's back inside B (one
reflection: rays guided along the layer by several reflections are not modelled). With
Fresnel partial reflection (``through_kernel``, ``fresnel_limits``, ``angle_landing_at``) a
ray crossing B is followed through its reflections at both faces up to the third pass.
A free thickness going to 0 leaves the interface A | C, smoothly: below the neutron's
evanescent depth the layer's values fade to A's (``_model._vanishing``).
Local frame and units as in ``_kernel``; angles are slopes (rad), lengths µm.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._kernel import AngularMass, deflected_kinks, in_plane_frame, straight_kinks

NEWTON_STEPS = 6  # for the incoming angle that lands at an edge after both faces
# µm or rad: keeps w / reach and w / u finite (and 0 for w = 0); its fourth power stays a normal
# float32 number, so that reverse-mode derivatives through 1 / u^2 stay finite in float32
TINY = 1e-9
_NEVER = 1.0  # rad: an angle limit no paraxial ray reaches


class ThinLayer(eqx.Module):
    """A coupled thin layer: media indices ``left`` (A), ``layer`` (B) and ``right`` (C).

    Media are indexed as in ``_model.Interface`` (0 and n_layer+1 vacuum); B's faces are
    the boundaries ``layer - 1`` and ``layer``.
    """

    left: int = eqx.field(static=True)
    layer: int = eqx.field(static=True)
    right: int = eqx.field(static=True)


def face_limits(restrict, z_lo, z_hi):
    """Angle limits of a thin layer's face as a function of the crossing depth z.

    restrict = (w, forward, reflect_k): w the layer's width (µm); forward: the face is
    the first one met (rays from outside, kept while they stay in B: outgoing angle
    below w / (z_hi - z)); otherwise the second (rays that started in B: incoming angle
    below w / (z - z_lo)); reflect_k (n_lam,) as in ``deflected_cumulative``. Returns
    z -> (straight ceiling, deflected-mass ceiling, outgoing ceiling), in rad.
    """
    w, forward = restrict[:2]

    def limits(z):
        reach = jnp.maximum(jnp.where(forward, z_hi - z, z - z_lo), TINY)
        cut = w / reach
        return cut, jnp.where(forward, _NEVER, cut), jnp.where(forward, cut, _NEVER)

    return limits


def fresnel_limits(restrict, limits, z, k):
    """(floor, ceiling) (rad) of the incoming angles of the rays that a thin layer's face
    refracts and keeps (``restrict`` and ``limits`` as in ``face_limits``; k (n_lam, 1, 1) the
    face's): above those it reflects (reflect_k), and for the first face those whose outgoing
    angle stays below the limit, sqrt(limit^2 + k); Fresnel reflection acts on these."""
    forward, reflect_k = restrict[1], restrict[2].reshape(k.shape)
    cut = limits(z)[0]
    return root(jnp.maximum(reflect_k, 0.0)) * (reflect_k > 0), jnp.where(forward, root(cut * cut + k), cut)


def root(x):
    """sqrt with finite derivatives where its argument is clipped at 0 (as ``_kernel._safe_sqrt``)."""
    return jnp.sqrt(jnp.maximum(x, TINY**2))


def _safe(d):
    return jnp.where(jnp.abs(d) > TINY, d, TINY)


def face_cuts(restrict, aim, distance_um, z_lo, z_hi, fan, k=None):
    """Depths where a face's limit (``face_limits``) makes a kink: where the edge's ray meets
    it (one, like aim) and where it crosses the ends of the fan ``fan`` = (a_min, a_max) seen from z = 0.

    k (n_lam, 1) for refracted rays: the second face's limit is on the incoming angle
    sqrt(g^2 + k) of the outgoing g = aim / (distance - z), found by a few fixed-point steps.
    """
    w, forward = restrict[:2]
    # the first face limits the outgoing angle of refracted rays, sqrt(a^2 - k) at a fan's end
    out = (lambda a: a) if k is None else (lambda a: root(jnp.maximum(a * a - k, 0.0)))
    ends = tuple(jnp.where(forward, z_hi - w / jnp.maximum(out(a), TINY), z_lo + w / jnp.maximum(a, TINY))
                 for a in fan)
    stays = (w * distance_um - aim * z_hi) / _safe(w - aim)  # aim / (distance - z) = w / (z_hi - z)
    started = (w * distance_um + aim * z_lo) / _safe(w + aim)  # aim / (distance - z) = w / (z - z_lo)
    if k is not None:  # left of the face the reflected rays land, at -(incoming angle)
        started = jnp.where(aim > 0, started, (w * distance_um - aim * z_lo) / _safe(w - aim))
        for _ in range(3):
            g = aim / (distance_um - jnp.clip(started, z_lo, z_hi))
            incoming = jnp.where(aim > 0, root(jnp.maximum(g * g + k, 0.0)), -g)
            started = z_lo + w / jnp.maximum(incoming, TINY)
    return (jnp.where(forward, stays, started),) + ends


def _weighted_mass(mass: AngularMass, angle_of, u_lo, u_hi, factor, nodes, weights, slope=None):
    """int factor(u) dM(angle_of(u)) over u in [u_lo, u_hi] (by parts, Gauss nodes on [0, 1]).

    factor: an elementwise function of u, e.g. ``_path_factor`` (the extra attenuation of a
    path w / u in B) times the share that Fresnel reflection lets through; slope: its
    derivative (default: by forward-mode differentiation). For a constant factor 1 this is
    the mass between angle_of(u_lo) and angle_of(u_hi), exactly.
    """
    u_lo, u_hi = jnp.broadcast_arrays(u_lo, u_hi)
    base = mass.primitive(angle_of(u_lo))
    along = np.asarray(nodes).reshape((-1,) + (1,) * u_lo.ndim)
    u = u_lo + (u_hi - u_lo) * along
    d_factor = jax.jvp(factor, (u,), (jnp.ones_like(u),))[1] if slope is None else slope(u)
    integral = jnp.tensordot(np.asarray(weights), d_factor * (mass.primitive(angle_of(u)) - base), 1)
    return factor(u_hi) * (mass.primitive(angle_of(u_hi)) - base) - (u_hi - u_lo) * integral


def _path_factor(c):
    """u -> exp(-c / u): the extra attenuation of a path w / u in B, c = (mu_B - mu_other) w."""
    return lambda u: jnp.exp(-c / jnp.maximum(u, TINY))


def _path_slope(c):
    """The derivative in u of ``_path_factor(c)``."""
    return lambda u: _path_factor(c)(u) * c / jnp.square(jnp.maximum(u, TINY))


def reflectivity(a, b):
    """Fresnel reflectivity ((a - b) / (a + b))^2 of a face between grazing angles a and b (rad)
    on its two sides, either direction; 1 where both are 0."""
    return jnp.square((a - b) / jnp.maximum(a + b, TINY))


def _fresnel_reflectivities(u, k_ab, kappa):
    """Fresnel reflectivities (R1, R2) (each like u) that a ray crossing B at angle u meets at
    the first face (from A at sqrt(u^2 + k_AB)) and at the second (into C at sqrt(u^2 + kappa));
    k_ab, kappa = k_AB - k_AC: as in ``through_kernel``."""
    return (reflectivity(root(u * u + k_ab), u), reflectivity(u, root(jnp.maximum(u * u + kappa, 0.0))))


def through_kernel(group, side, distance_um, wavelength_weight, depth_um, edges_um, depth_nodes):
    """Cumulative kernels (T, T_att) (n_window_edges,) of the rays that cross both faces.

    side, in the local frame: the first face's boundary at z = 0, its slope and
    z-centre, mu of A, B, C (n_lam,), k_AB and k_AC (n_lam,), the width w (µm) and the
    assignment plane (``_model._assignment_planes``).
    As ``_model._crossing_kernel``, the step assignment of these rays (A, B or C by
    where the straight ray is at z = 0) is subtracted. depth_nodes:
    ``_model._kink_aligned_depths``. The attenuation in B is integrated over angle on
    the group's ``thin_nodes``.
    """
    boundary, slope, z_mid, mu_a, mu_b, mu_c, k_ab, k_ac, w, plane = side
    boundary, z_mid, distance_um = in_plane_frame(boundary, slope, z_mid, distance_um, plane)
    z_lo, z_hi = z_mid - 0.5 * depth_um, z_mid + 0.5 * depth_um
    L = group.aperture_distance_um
    gauss = (group.thin_nodes, group.thin_weights)

    def mass_at(z):
        return AngularMass(group.aperture, boundary + slope * z, slope, L - distance_um + z, group.aperture_um,
                           floor=w / jnp.maximum(z_hi - z, TINY))

    def nodes(kinks, aim, cuts):
        z, dz = depth_nodes(mass_at, kinks, aim, distance_um, z_lo, z_hi, group, cuts)
        return z, dz * L / (L - distance_um + z), aim[..., None, :] / (distance_um - z)

    per_lam = (-1, 1, 1)
    aim = edges_um - (boundary + slope * distance_um)  # (e,)
    transmitted = [wavelength_weight @ jnp.exp(-mu * depth_um) for mu in (mu_a, mu_b, mu_c)]

    # Straight rays (T_att and the step assignment): those reaching the second face, a >= w / (z_hi - z).
    view = AngularMass(group.aperture, boundary, slope, L - distance_um, group.aperture_um)  # from z = 0
    reach = face_cuts((w, True), aim, distance_um, z_lo, z_hi, (view.a_min, view.a_max))  # a = w / (z_hi - z)
    in_b = w * distance_um / _safe(w - aim)  # a = w / -z: the ray is in B at z = 0 from here on
    z, scale, grazing = nodes(straight_kinks, aim, reach + (in_b,))  # (N, e)
    mass = mass_at(z)
    end = jnp.clip(grazing, mass.a_min, mass.a_max)
    split = jnp.clip(w / jnp.maximum(-z, TINY), mass.a_min, end)  # below: still in B at z = 0
    base = mass.primitive(mass.a_min)
    stepped = jnp.where(z > 0, transmitted[0] * (mass.primitive(end) - base),
                        transmitted[1] * (mass.primitive(split) - base)
                        + transmitted[2] * (mass.primitive(end) - mass.primitive(split)))
    stepped = jnp.sum(stepped * scale, axis=-2)
    outside = jnp.exp(-mu_a.reshape(per_lam) * (z - z_lo) - mu_c.reshape(per_lam) * (z_hi - z))  # (l, N, e)
    c = ((mu_b - mu_c) * w).reshape(per_lam)
    lo, end, _ = jnp.broadcast_arrays(mass.a_min, end, c)  # (l, N, e)
    straight = _weighted_mass(mass, lambda a: a, lo, end, _path_factor(c), *gauss, _path_slope(c))
    attenuation = jnp.sum(jnp.tensordot(wavelength_weight, outside * straight, 1) * scale, axis=-2) - stepped

    # Refracted rays: u = sqrt(a^2 - k_AB) in B, above w / (z_hi - z) and above the second face's
    # critical angle sqrt(k_AC - k_AB); they land at w + a_C (Delta - z - w / u).
    k_ab_l, k_ac_l = k_ab[:, None], k_ac[:, None]
    aim_l = jnp.broadcast_to(aim, (k_ab.shape[0],) + aim.shape)
    # kinks: where the edge's ray is the one from u = w / (z_hi - z), and where that floor
    # meets the second face's critical angle
    kappa_l = k_ab_l - k_ac_l
    u_edge = root(jnp.maximum(jnp.square((aim_l - w) / (distance_um - z_hi)) - kappa_l, 0.0))
    floor_cut = jnp.where((aim_l > w) & (u_edge > 0), z_hi - w / jnp.maximum(u_edge, TINY), z_hi)
    critical_cut = z_hi - w / jnp.maximum(root(jnp.maximum(-kappa_l, 0.0)), TINY)
    def end_cut(a):  # where the edge's ray is the one that came in at angle a (the fan's ends)
        u_end = root(jnp.maximum(a * a - k_ab_l, 0.0))
        out = root(jnp.maximum(a * a - k_ac_l, 0.0))
        return distance_um - (aim_l - w) / jnp.maximum(out, TINY) - w / jnp.maximum(u_end, TINY)

    floor_ends = tuple(z_hi - w / jnp.maximum(root(jnp.maximum(a * a - k_ab_l, 0.0)), TINY)
                       for a in (view.a_min, view.a_max))  # u = w / (z_hi - z) at the fan's ends
    cuts = (floor_cut, critical_cut, end_cut(view.a_min), end_cut(view.a_max)) + floor_ends
    k_ab_n, kappa = k_ab.reshape(per_lam), (k_ab - k_ac).reshape(per_lam)

    z, scale, grazing = nodes(lambda m: deflected_kinks(m, k_ac_l, aim_l > 0), aim_l, cuts)
    mass = AngularMass(group.aperture, boundary + slope * z, slope, L - distance_um + z, group.aperture_um)
    u_floor = jnp.maximum(w / jnp.maximum(z_hi - z, TINY), root(jnp.maximum(-kappa, 0.0)))
    a_lo = jnp.clip(root(jnp.maximum(u_floor**2 + k_ab_n, 0.0)), mass.a_min, mass.a_max)
    u_lo = root(jnp.maximum(a_lo**2 - k_ab_n, 0.0))
    u_hi = jnp.maximum(root(jnp.maximum(mass.a_max**2 - k_ab_n, 0.0)), u_lo)
    incoming = lambda v: jnp.clip(root(jnp.maximum(v * v + k_ab_n, 0.0)), a_lo, mass.a_max)
    lever = distance_um - z
    u = angle_landing_at(aim_l[..., None, :], lever, w, kappa, 1, 1, u_lo, u_hi)
    outside = jnp.exp(-mu_a.reshape(per_lam) * (z - z_lo) - mu_c.reshape(per_lam) * (z_hi - z))
    if not group.fresnel_nodes:
        refracted = _weighted_mass(mass, incoming, u_lo, u, _path_factor(c), *gauss, _path_slope(c))
        return wavelength_weight @ jnp.sum(outside * refracted * scale, axis=-2) - stepped, attenuation
    # Fresnel: a ray crossing B at u goes on into C with (1 - R1)(1 - R2); with R1 the first face
    # reflects it (it leaves at -a from depth z); with (1 - R1) R2 the second face sends it back:
    # it leaves the first face at -a from depth z + 2 w / u with 1 - R1, or, beyond the back, B
    # itself at -u; the first face turns R1 of these back again, on into C after three passes or
    # out of the back of B (further bounces, third order in R, are left out).
    reflectivities = lambda v: _fresnel_reflectivities(v, k_ab_n, kappa)
    # R1 and R2 have square-root kinks at the critical angles, which sit at the lower end u_lo:
    # nodes u = lo + (hi - lo) t^2 (Gauss in t) integrate them as smooth functions
    t, weight = (np.asarray(v) for v in gauss)
    near_lo = (tuple(t * t), tuple(2.0 * t * weight))
    on = lambda v: _path_factor(c)(v) * (1.0 - reflectivities(v)[0]) * (1.0 - reflectivities(v)[1])
    second = lambda v: (1.0 - reflectivities(v)[0]) * reflectivities(v)[1]
    again = lambda v: second(v) * reflectivities(v)[0]
    turn = jnp.clip(2.0 * w / jnp.maximum(z_hi - z, TINY), u_lo, u_hi)  # above it they return before the back
    third = jnp.clip(3.0 * w / jnp.maximum(z_hi - z, TINY), turn, u_hi)  # ... and reach C again
    u_third = angle_landing_at(aim_l[..., None, :], lever, w, kappa, 3, 1, third, u_hi)
    refracted = (_weighted_mass(mass, incoming, u_lo, u, on, *near_lo)
                 + _weighted_mass(mass, incoming, third, u_third, lambda v: _path_factor(c)(v) * again(v),
                                  *near_lo))
    behind_from = jnp.clip((2.0 * w - aim_l[..., None, :]) / lever, u_lo, turn)  # landing 2 w - u lever
    behind_to = jnp.clip((aim_l[..., None, :] + 2.0 * w) / lever, turn, third)  # landing u lever - 2 w
    behind = (_weighted_mass(mass, incoming, behind_from, turn, second, *near_lo)
              + _weighted_mass(mass, incoming, turn, behind_to, again, *near_lo))
    in_b_path = jnp.exp(-mu_a.reshape(per_lam) * (z - z_lo) - mu_b.reshape(per_lam) * (z_hi - z))
    first_from = root(jnp.maximum(jnp.clip(-grazing, a_lo, mass.a_max) ** 2 - k_ab_n, 0.0))
    first = _weighted_mass(mass, incoming, jnp.clip(first_from, u_lo, u_hi), u_hi, lambda v: reflectivities(v)[0],
                           *near_lo)
    back_from = angle_landing_at(aim_l[..., None, :], lever, w, k_ab_n, 2, -1, turn, u_hi)
    c_back = ((mu_b - mu_a) * 2.0 * w).reshape(per_lam)
    back = _weighted_mass(mass, incoming, back_from, u_hi,
                          lambda v: _path_factor(c_back)(v) * second(v) * (1.0 - reflectivities(v)[0]), *near_lo)
    reflected_path = jnp.exp(-mu_a.reshape(per_lam) * depth_um)
    deflected = wavelength_weight @ jnp.sum(
        (outside * refracted + in_b_path * behind + reflected_path * (first + back)) * scale, axis=-2)
    return deflected - stepped, attenuation


def guided_kernel(group, side, distance_um, wavelength_weight, depth_um, edges_um):
    """Cumulative kernels (T, 0) of the rays guided in B: they entered through its front,
    move towards the second face and are totally reflected at both faces (a below
    ``trapped``, n_lam). Unfolded, such a ray from x0 in [0, w] runs straight to
    x0 + a depth; folded into [0, w] (period 2w), it leaves the back at that position,
    at +a or -a. Replaces the straight landing of those that reach no face (the step
    profile's); those that reach one are left out of ``_crossing_kernel`` (its floor).
    side: the first face's boundary at z = 0, slope, z-centre, mu_B (n_lam,),
    trapped (n_lam,) rad, w µm, the assignment plane. Midpoint rule over angle on
    ``group.guided_cells`` cells.
    """
    boundary, slope, z_mid, mu_b, trapped, w, plane = side
    boundary, z_mid, distance_um = in_plane_frame(boundary, slope, z_mid, distance_um, plane)
    z_lo, z_hi = z_mid - 0.5 * depth_um, z_mid + 0.5 * depth_um
    L = group.aperture_distance_um
    front = AngularMass(group.aperture, boundary + slope * z_lo, slope, L - distance_um + z_lo, group.aperture_um)
    aim = edges_um - (boundary + slope * distance_um)  # (e,)
    lo = front.a_min
    hi = jnp.clip(trapped, lo, front.a_max)[:, None]  # (l, 1)
    cell = lo + (hi - lo) * np.linspace(0.0, 1.0, group.guided_cells + 1)[:, None, None]  # (n + 1, l, 1)
    density = jnp.diff(front.cdf(cell), axis=0)  # the rays of each cell, exactly
    a = 0.5 * (cell[1:] + cell[:-1])  # (n, l, 1)
    width = jnp.maximum(w, TINY)
    run = a * depth_um
    turns = jnp.floor(run / width)
    r = run - turns * width
    even = jnp.mod(turns, 2.0) == 0
    out = distance_um - z_hi
    count = lambda x, n: jnp.clip(x, 0.0, n)  # uniform rays over a length n landing left of an edge at x
    first = jnp.where(even, count(aim - a * out - r, width - r), count(aim + a * out, width - r))
    second = jnp.where(even, count(aim + a * out - (width - r), r), count(aim - a * out, r))
    straight = count(aim - a * (distance_um - z_lo), jnp.maximum(width - run, 0.0))
    guided = jnp.sum(density * (first + second - straight), axis=0)  # (l, e)
    return wavelength_weight @ (jnp.exp(-mu_b * depth_um)[:, None] * guided), jnp.zeros_like(aim)


def angle_landing_at(aim, lever, w, k_out, passes, sign, lo, hi):
    """The angle x in B (clipped to [lo, hi]) of the ray that crosses B ``passes`` times before it
    leaves at y = sqrt(x^2 + k_out) and lands at ``aim`` (µm, from the face it entered B by, or
    for sign -1 from the face that reflected it).

    sign +1: it leaves through the second face, onward (w + y (lever - passes w / x) = aim);
    -1: it leaves through the first face, back (y (lever - passes w / x) + (2 - passes) w = -aim;
    passes 1: reflected at the second face, 2: entered and returned). The landing is monotonic
    in x wherever x > passes w / lever. Newton steps from the solution for w = 0.
    """
    offset = w if sign > 0 else (2 - passes) * w

    def newton(x):
        y, safe = root(x * x + k_out), jnp.maximum(x, TINY)
        arm = lever - passes * w / safe
        value = y * arm + offset - sign * aim
        slope = x / y * arm + y * passes * w / (safe * safe)
        return jnp.clip(x - value / jnp.maximum(slope, TINY), lo, hi)

    first = (sign * aim - offset) / lever
    x = jnp.clip(root(jnp.maximum(first * jnp.abs(first) - k_out, 0.0)), lo, hi)
    for _ in range(NEWTON_STEPS - 1):
        x = newton(x)
    # the last step from the converged root, held constant, carries the derivatives: at a
    # root they are the implicit ones, -(d value / d parameter) / slope, and reverse mode
    # differentiates one step rather than all of them
    return newton(jax.lax.stop_gradient(x))

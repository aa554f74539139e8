"""The forward model: transmission T(x) and attenuation-only T_att(x) for every profile.

T = T_step + sum over interfaces and crossing directions of a deflection kernel.

- ``T_step``: each ray is given the layer it is in at the sample's mid-plane
  (z = 0), attenuated by exp(-mu * depth) and projected from the whole aperture
  (penumbra Delta * D / L, magnification L / (L - Delta)); closed form per pixel.
- The kernel of an interface (``_kernel.py``) replaces, for the rays that cross
  it inside the sample, the step assignment by their true path: straight (T_att)
  or refracted / totally reflected (T), and with the Fresnel option partially
  reflected above the critical angle. Interfaces act independently: exact when
  every layer is thicker than the sideways drift depth * |angle| (~20 µm at 2 mm
  depth), an approximation for thinner layers. Its depth integral is split, per
  detector edge, where the integrand kinks, so the model is smooth in its parameters.
- Detector blur (Gaussian) and pixel integration close the chain.

Internal units: µm, rad, Å; mu in 1/µm. Use float64 (``jax_enable_x64``) for
fitting; float32 agrees to ~1e-4 in T.
"""

from __future__ import annotations

import dataclasses
import functools
import statistics
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from . import _thin
from .._aperture import APERTURES
from .._grouped import GroupedModel
from .._kernel import (AngularMass, deflected_and_fresnel_kinks, deflected_cumulative, deflected_kinks, fresnel_kinks,
                      fresnel_transfer, in_plane_frame, landing_range, landing_regions, straight_cumulative,
                      straight_kinks)

_TINY_ANGLE = 1e-12  # rad: a kink angle this small is never reached from the edge
DEPTH_PIECES = 4  # smooth pieces of the depth integral: two kinks and the mid-plane, or three kinks
# µm: a layer much thinner than this is transparent (the neutron's evanescent depth,
# ~ lambda / (4 pi theta_c), is ~0.01 µm); see ``_vanishing``
TUNNEL_UM = 0.02
# A CPU evaluates a group's profiles and a profile's crossing sides in chunks of kernel arrays
# at most this large (elements): ``_per_chunk``
_CPU_CHUNK_ELEMENTS = 2**15


class ModelParams(eqx.Module):
    """Traced parameters, in the units of the scene keys.

    Per layer (n_layer,): thickness_um, sld_e6_per_A2, mu_per_m, mu_per_m_per_A, and
    density_scale (multiplies the SLD and the whole mu(lambda), tabulated part included);
    roughness_mrad (RMS normal slope of the layer's right-hand face); sld_end_e6_per_A2 and
    mu_end_per_m (right-hand values, used for the layers the model's ``graded`` marks).
    left_roughness_mrad: the stack's first face.
    Per profile (n_profile,): distance_mm, shift_um (lateral shift of the profile).
    """

    thickness_um: Float[Array, " layer"]
    sld_e6_per_A2: Float[Array, " layer"]
    mu_per_m: Float[Array, " layer"]
    mu_per_m_per_A: Float[Array, " layer"]
    density_scale: Float[Array, " layer"]
    roughness_mrad: Float[Array, " layer"]
    sld_end_e6_per_A2: Float[Array, " layer"]
    mu_end_per_m: Float[Array, " layer"]
    left_roughness_mrad: Float[Array, ""]
    tilt_deg: Float[Array, ""]
    centre_um: Float[Array, ""]
    depth_mm: Float[Array, ""]
    distance_mm: Float[Array, " profile"]
    shift_um: Float[Array, " profile"]


class Interface(eqx.Module):
    """An interface at boundary ``position`` between media ``left`` and ``right``.

    Media are indexed 0 (vacuum), 1..n_layer, n_layer+1 (vacuum); zero-thickness
    layers are skipped, so left and right need not be neighbours.
    """

    position: int = eqx.field(static=True)
    left: int = eqx.field(static=True)
    right: int = eqx.field(static=True)
    refracting: bool = eqx.field(static=True)
    rough: bool = eqx.field(static=True)  # its normal slope is averaged over (``rough_nodes``)


class ProfileGroup(eqx.Module):
    """Profiles sharing one static plan (grid, windows, quadrature), batched with vmap
    (on a CPU in chunks, ``_per_chunk``).

    The grid is each profile's pixels, split into ``n_sub`` sub-bins of
    ``bin_um`` and padded by ``n_pad`` sub-bins per side for the detector blur.
    """

    index: tuple[int, ...] = eqx.field(static=True)  # positions in the scene's profile list
    aperture: str = eqx.field(static=True)
    aperture_um: float = eqx.field(static=True)
    aperture_distance_um: float = eqx.field(static=True)
    psf_sigma_um: float = eqx.field(static=True)
    bin_um: float = eqx.field(static=True)
    n_edges: int = eqx.field(static=True)
    n_sub: int = eqx.field(static=True)
    n_pad: int = eqx.field(static=True)
    window: int = eqx.field(static=True)  # kernel window half-width, sub-bins
    # Fresnel partial reflection: Gauss-Legendre on [0, 1] for ``_kernel.fresnel_transfer``; () when off
    fresnel_nodes: tuple[float, ...] = eqx.field(static=True)
    fresnel_weights: tuple[float, ...] = eqx.field(static=True)
    rough_strata: int = eqx.field(static=True)  # rough faces: equiprobable strata of the normal tilt; 0 when none
    # coupled thin layers: Gauss-Legendre on [0, 1] for the attenuation in the layer; () without
    thin_nodes: tuple[float, ...] = eqx.field(static=True)
    thin_weights: tuple[float, ...] = eqx.field(static=True)
    guided_cells: int = eqx.field(static=True)  # angle cells of the rays guided in a thin layer
    thin_z_nodes: tuple[float, ...] = eqx.field(static=True)  # depth nodes per piece of the thin kernels
    thin_z_weights: tuple[float, ...] = eqx.field(static=True)
    z_nodes: tuple[float, ...] = eqx.field(static=True)  # Gauss-Legendre on [0, 1], per depth piece
    z_weights: tuple[float, ...] = eqx.field(static=True)
    first_edge_um: Float[Array, " group"]
    wavelength_A: Float[Array, "group lam"]
    wavelength_weight: Float[Array, "group lam"]
    mu_table_per_m: Float[Array, "group lam layer"]
    step_wavelength_A: Float[Array, "group fine"]  # finer nodes for the step profile's plateaus
    step_weight: Float[Array, "group fine"]
    step_mu_table_per_m: Float[Array, "group fine layer"]
    # edges of each (tilt, wavelength) sample's two sub-windows of the deflected kernels (``_sub_windows``);
    # (): the whole window
    sub_window: tuple[int, ...] = eqx.field(static=True, default=())
    straight_window: int = eqx.field(static=True, default=0)  # ... of the straight rays (0: the whole window)


class ForwardModel(GroupedModel):
    """Predicts (T, T_att) for every profile of a scene; build it with ``build_model``."""

    groups: tuple[ProfileGroup, ...]
    interfaces: tuple[Interface, ...]
    n_profiles: int = eqx.field(static=True)
    graded: tuple[bool, ...] = eqx.field(static=True)  # per layer: SLD and mu linear across it
    step_pieces: int = eqx.field(static=True)  # uniform pieces of a graded layer in the step profile
    thin: tuple[_thin.ThinLayer, ...] = ()  # coupled thin layers; their faces are not in ``interfaces``
    # (layer, left neighbour) media indices of the layers whose thickness is free (``_vanishing``)
    vanishing: tuple[tuple[int, int], ...] = eqx.field(static=True, default=())

    def stacked(self, params: ModelParams) -> tuple[tuple[Array, Array], ...]:
        """Pixel-averaged (T, T_att) per group, each (n_group_profiles, n_pixel), rows in
        ``group.index`` order: the traced graph does not grow with the profiles of a group."""
        out = []
        n_sides = 2 * (len(self.interfaces) + 2 * len(self.thin))  # crossing sides of a profile, at most
        for group in self.groups:
            index = np.asarray(group.index)
            args = (params.distance_mm[index], params.shift_um[index], group.first_edge_um,
                    (group.wavelength_A, group.wavelength_weight, group.mu_table_per_m),
                    (group.step_wavelength_A, group.step_weight, group.step_mu_table_per_m))
            T_g, T_att_g = _in_chunks(lambda a: _profile(group, self, params, *a), args,
                                      _per_chunk(len(index), n_sides * _side_elements(group)))
            blur_and_bin = jax.vmap(lambda values: _blur_and_bin(group, values))  # one op for all rows
            out.append((blur_and_bin(T_g), blur_and_bin(T_att_g)))
        return tuple(out)

    @staticmethod
    def group_pixels(group) -> int:
        return (group.n_edges - 1 - 2 * group.n_pad) // group.n_sub


def _media(params: ModelParams, wavelength_A, mu_table_per_m, graded=(), vanishing=()):
    """SLD (n_layer+2,) in 1e-6 Å^-2 and mu (n_lam, n_layer+2) in 1/µm, vacuum at both ends:
    (sld, mu) at each layer's left-hand side, then at its right-hand side (the same arrays
    unless a layer is ``graded``). vanishing: (layer, left neighbour) media indices of the
    layers whose thickness is free (``_vanishing``)."""
    zero = jnp.zeros((1,), params.sld_e6_per_A2.dtype)
    pad = lambda values: jnp.concatenate([zero, params.density_scale * values, zero])
    sld = pad(params.sld_e6_per_A2)
    mu = params.density_scale * (params.mu_per_m + params.mu_per_m_per_A * wavelength_A[:, None]
                                 + mu_table_per_m)
    mu = jnp.pad(mu * 1e-6, ((0, 0), (1, 1)))
    if not any(graded):
        return _vanishing(params.thickness_um, vanishing, sld, mu, sld, mu)
    mask = np.asarray(graded)
    sld_end = pad(jnp.where(mask, params.sld_end_e6_per_A2, params.sld_e6_per_A2))
    mu_end = mu + 1e-6 * pad(jnp.where(mask, params.mu_end_per_m - params.mu_per_m, 0.0))
    return _vanishing(params.thickness_um, vanishing, sld, mu, sld_end, mu_end)


def _vanishing(thickness_um, vanishing, sld, mu, sld_end, mu_end):
    """Media (sld, mu, sld_end, mu_end as ``_media``) with each layer of ``vanishing`` made
    transparent below the neutron's evanescent depth: its values fade to its left
    neighbour's right-hand ones with weight 1 - exp(-(t / TUNNEL_UM)^2) (smooth, 0 with zero
    slope at t = 0, 1 within 1e-6 from t = 0.075 µm). At t = 0 its left face has no contrast
    (its kernels add exactly nothing) and its right face is the neighbours' interface, so a
    free thickness going to 0 leaves the model without the layer, whatever its material."""
    for layer, left in vanishing:
        hidden = jnp.exp(-jnp.square(thickness_um[layer - 1] / TUNNEL_UM))  # 1 - the weight
        only = np.arange(sld.shape[-1]) == layer  # elementwise, not a scatter: cheaper to compile
        towards = sld_end[left], mu_end[:, left, None]

        def fade(values, to):
            return values + only * hidden * (to - values[..., layer, None])

        sld, sld_end = fade(sld, towards[0]), fade(sld_end, towards[0])
        mu, mu_end = fade(mu, towards[1]), fade(mu_end, towards[1])
    return sld, mu, sld_end, mu_end


def _step_jumps(model, params: ModelParams, boundary_um, plane_um, step_spectrum, depth_um, distance_um):
    """Positions (n_jump,) µm of the step profile's jumps in their assignment planes, those
    planes' depths z (µm), the jumps in the spectrum-averaged transmission, and the shift (µm)
    of the rays of each jump (None when no layer is graded). boundary_um, plane_um: each
    boundary in its plane and that plane (``_assignment_planes``). A graded layer is
    ``step_pieces`` uniform pieces whose rays the SLD
    gradient bends by depth x d(delta)/dx (paraxial prism, at the spectrum's mean lambda^2):
    they land depth x distance x d(delta)/dx further towards lower delta. Each jump between
    pieces of different shifts is then two: +t_right at the right piece's shift, -t_left at
    the left's."""
    step_lam, step_weight, step_table = step_spectrum
    sld, mu, sld_end, mu_end = _media(params, step_lam, step_table, model.graded, model.vanishing)
    if not any(model.graded):
        return boundary_um, plane_um, jnp.diff(step_weight @ jnp.exp(-mu * depth_um)), None
    medium, fraction, left, at = [0], [0.0], [0], [0.0]  # pieces; jumps: left boundary + fraction
    for i, graded in enumerate(model.graded):
        n = model.step_pieces if graded else 1
        medium += [i + 1] * n
        fraction += list((np.arange(n) + 0.5) / n)
        left += [i] * n
        at += list(np.arange(1, n + 1) / n)
    medium, fraction, left, at = (np.asarray(v) for v in (medium + [len(model.graded) + 1],
                                                          fraction + [0.0], left, at))
    mu_piece = mu[:, medium] + (mu_end[:, medium] - mu[:, medium]) * fraction
    transmitted = step_weight @ jnp.exp(-mu_piece * depth_um)
    positions = boundary_um[left] + (boundary_um[left + 1] - boundary_um[left]) * at
    planes = plane_um[left] + (plane_um[left + 1] - plane_um[left]) * at  # within each piece's depths
    thickness = jnp.concatenate([jnp.ones((1,), sld.dtype), params.thickness_um, jnp.ones((1,), sld.dtype)])
    delta_slope = (step_weight @ step_lam**2) * 1e-6 / (2 * jnp.pi) * (sld_end - sld) / jnp.maximum(thickness, 1e-9)
    shift = -depth_um * distance_um * delta_slope[medium]  # per piece
    twice = lambda values: jnp.concatenate([values, values])
    return (twice(positions), twice(planes), jnp.concatenate([transmitted[1:], -transmitted[:-1]]),
            jnp.concatenate([shift[1:], shift[:-1]]))


def _boundaries(params: ModelParams, shift_um):
    """Boundaries at the mid-plane z = 0 (n_layer+1,), their slope dx/dz, and z-centres (µm)."""
    tilt = jnp.deg2rad(params.tilt_deg)
    cumulative = jnp.concatenate([jnp.zeros((1,), params.thickness_um.dtype),
                                  jnp.cumsum(params.thickness_um)])
    across = cumulative - 0.5 * cumulative[-1]  # sample frame, from the stack centre
    return params.centre_um + shift_um + across / jnp.cos(tilt), jnp.tan(tilt), -across * jnp.sin(tilt)


def _assignment_planes(model, z_mid_um, depth_um):
    """Depth z (µm, (n_layer+1,)) at which the step profile gives each ray the side of each
    boundary it is on: the mid-plane z = 0, or the nearer end of the face where the face lies
    wholly before or after it (a wide, tilted layer: a ray that crosses the face's line between
    the face's end and the mid-plane crosses no face, and must not change sides there). Both
    faces of a coupled thin layer take its first face's plane (its kernels share one frame)."""
    plane = jnp.clip(0.0, z_mid_um - 0.5 * depth_um, z_mid_um + 0.5 * depth_um)
    for layer in model.thin:
        plane = plane.at[layer.layer].set(plane[layer.layer - 1])
    return plane


def _step_profile(group: ProfileGroup, boundary_um, jump, distance_um, edges_um, shift_um=None):
    """Bin averages (n_edges-1,) of the step profile seen through the aperture.

    Each jump (n_jump,) sits at boundary_um in its assignment plane, distance_um (n_jump,)
    from the detector. A ray through that plane's point x0 reaching detector point X left the
    aperture at x_ap = (x0 L - X (L - Delta)) / Delta; the fraction of the aperture that sees
    x0 > b is 1 - cdf(2 x_ap / D), integrated over the bin in closed form. shift_um
    (per jump, optional): the jump's rays land that much further (a graded layer's prism).
    """
    _, _, cdf_integral = APERTURES[group.aperture]
    L, D = group.aperture_distance_um, group.aperture_um
    distance_um = distance_um[:, None]
    to_sample = L - distance_um
    landing = edges_um[None, :] if shift_um is None else edges_um[None, :] - shift_um[:, None]
    s = 2.0 * (boundary_um[:, None] * L - landing * to_sample) / (distance_um * D)
    K = cdf_integral(s)
    beyond = 1.0 - distance_um * D / (2.0 * to_sample * group.bin_um) * (K[:, :-1] - K[:, 1:])
    return 1.0 + jump @ beyond


def _kink_aligned_depths(mass_at, kinks, aim_um, distance_um, z_lo, z_hi, group: ProfileGroup, extra_cuts=(),
                         mid_plane=True):
    """Depth nodes and weights (..., pieces n, e) of Gauss-Legendre on [z_lo, z_hi], split where the integrand kinks.

    The ray from depth z to an edge grazes the interface at aim_um / (distance_um - z);
    the cumulative (``_kernel``) has a kink in z where that angle meets one of the
    ``kinks(mass)`` angles (two, or three for ``deflected_and_fresnel_kinks``), which depend on
    z only through the aperture's view. Splitting there, and (``mid_plane``) at the mid-plane
    z = 0 where the step assignment jumps (where it lies between z_lo and z_hi), keeps every
    piece smooth, so the kernel is smooth in the parameters rather than piecewise linear.
    aim_um: (..., e) µm, one value per edge. extra_cuts: more depths (each broadcastable to
    aim_um) to split at, one more piece each (a thin layer's kinks). Two kinks and the
    mid-plane, or three kinks without it, make ``DEPTH_PIECES`` pieces.
    """
    def depth_at(angle):  # where the ray to the edge grazes at ``angle``; z_hi if never
        reaches = jnp.abs(angle) > _TINY_ANGLE
        z = distance_um - aim_um / jnp.where(reaches, angle, 1.0)
        return jnp.where(reaches, jnp.clip(z, z_lo, z_hi), z_hi)

    # The kink angles from the mid-plane's view, then once more from the depths found:
    # the view changes by ~z / L, so one step leaves the cuts ~1e-4 µm off the kinks.
    depths = [depth_at(angle) for angle in kinks(mass_at(jnp.zeros_like(aim_um[..., :1])))]
    refined = kinks(mass_at(jnp.stack(depths)))
    depths = [depth_at(angle[i]) for i, angle in enumerate(refined)]
    # the mid-plane within the face's depths: a face of a wide tilted layer may lie wholly before or after it
    mid = jnp.clip(jnp.zeros_like(depths[0]), z_lo, z_hi)
    ends = jnp.full_like(mid, z_lo)[..., None, :], jnp.full_like(mid, z_hi)[..., None, :]
    inside = _sorted_three(*depths, mid) if mid_plane else _sorted_three(*depths)  # z_lo <= each <= z_hi
    cuts = jnp.concatenate([ends[0], inside, ends[1]], axis=-2)
    if extra_cuts:
        more = jnp.stack([jnp.clip(jnp.broadcast_to(c, mid.shape), z_lo, z_hi) for c in extra_cuts], axis=-2)
        cuts = jnp.sort(jnp.concatenate([cuts, more], axis=-2), axis=-2)
    # Gauss-Legendre in the log of the lever (distance - z) on every piece: the grazing
    # angle to an edge goes like 1 / lever, which is far from polynomial in z at short
    # distances (the lever runs from distance - depth / 2 to distance + depth / 2).
    log_lever = jnp.log(distance_um - cuts)
    length = jnp.diff(log_lever, axis=-2)[..., None, :]  # (..., pieces, 1, e), negative
    unit_nodes, unit_weights = (np.asarray(v)[:, None] for v in (group.z_nodes, group.z_weights))
    lever = jnp.exp(log_lever[..., :-1, None, :] + length * unit_nodes)  # (..., pieces, n, e)
    z, dz = distance_um - lever, -lever * length * unit_weights
    shape = aim_um.shape[:-1] + (-1, aim_um.shape[-1])
    return z.reshape(shape), dz.reshape(shape)


def _sorted_three(first, second, third):
    """The three arrays sorted elementwise, stacked on axis -2 (min-max network: XLA's sort is
    a comparator loop on a CPU, several times slower here)."""
    low, high = jnp.minimum(first, second), jnp.maximum(first, second)
    return jnp.stack([jnp.minimum(low, third), jnp.clip(third, low, high), jnp.maximum(high, third)], axis=-2)


def _crossing_kernel(group: ProfileGroup, side, distance_um, wavelength_weight, depth_um,
                     refracting: bool, rough: bool, edges_um, restrict=None):
    """Cumulative kernels (T, T_att), each (n_window_edges,), of one crossing direction.

    ``side`` holds, in the local frame where rays cross left to right: the boundary
    at z = 0, its slope, its z-centre, mu before and after (n_lam,),
    k = 2 (delta_after - delta_before) (n_lam,), the RMS slope of the face's normal
    (rad) and its assignment plane (``_assignment_planes``). The straight and the deflected
    terms are summed over depth nodes aligned with their own kinks (``_kink_aligned_depths``);
    the Fresnel transfer shares the deflected terms' nodes, split at the kinks of both (a thin
    layer's face: nodes of its own). The kernel replaces the crossing rays' step assignment by
    their true path in its own wavelength quadrature, so that an interface without
    contrast adds exactly nothing. With the group's ``straight_window`` and ``sub_window`` (not
    for a thin layer's face) the straight and the deflected rays are evaluated only on the edges
    where they land (``_covering_start``, ``_deflected_rays``). A rough face's deflected rays
    are averaged over its normal's tilt (``_tilt_quantiles``): at tilt t the rays meet the face
    at a' = a - t, leave at t + (the sharp face's outgoing angle at a'), and those with a <= t
    pass straight (``AngularMass``). restrict: a face of a coupled thin layer keeps only some
    of its rays (``_thin.face_limits``; not rough): (w, forward, reflect_k, guided angle, k_AB,
    mu_A) of its layer B between A and C; with Fresnel reflection the rays its second face
    reflects cross B back into A (``_kernel.fresnel_transfer``'s ``returning``).
    """
    boundary, slope, z_mid, mu_from, mu_to, k, slope_rms, plane = side
    boundary, z_mid, distance_um = in_plane_frame(boundary, slope, z_mid, distance_um, plane)
    z_lo, z_hi = z_mid - 0.5 * depth_um, z_mid + 0.5 * depth_um
    L = group.aperture_distance_um
    limits = None if restrict is None else _thin.face_limits(restrict, z_lo, z_hi)

    def mass_at(z, tilt=None, deflected=False, fresnel=False):
        source_to_z = L - distance_um + z
        floor = ceiling = None
        if limits is not None and fresnel:
            floor, ceiling = _thin.fresnel_limits(restrict, limits, z, k.reshape(-1, 1, 1))
        elif limits is not None:
            ceiling = limits(z)[int(deflected)]
        return AngularMass(group.aperture, boundary + slope * z, slope, source_to_z, group.aperture_um, tilt,
                           floor, ceiling)

    def nodes(kinks, aim, tilt=None, deflected=False, more_cuts=(), fresnel=False, mid_plane=True):
        """Depths z (..., N, e), weights x magnification, the aperture's view and grazing there."""
        if restrict is None:
            cuts = ()
        else:
            view = AngularMass(group.aperture, boundary, slope, L - distance_um, group.aperture_um)
            cuts = _thin.face_cuts(restrict, aim, distance_um, z_lo, z_hi, (view.a_min, view.a_max),
                                   k[:, None] if deflected else None) + more_cuts
        z, dz = _kink_aligned_depths(lambda z: mass_at(z, tilt, deflected), kinks, aim, distance_um, z_lo, z_hi,
                                     group, cuts, mid_plane)
        node_tilt = None if tilt is None else tilt[..., None]
        return (z, dz * L / (L - distance_um + z), mass_at(z, node_tilt, deflected, fresnel),
                aim[..., None, :] / (distance_um - z))

    per_lam = (-1, 1, 1)  # per-wavelength values against (N, e) or (l, N, e) nodes
    mu_from_l, mu_to_l = mu_from.reshape(per_lam), mu_to.reshape(per_lam)
    aim = edges_um - (boundary + slope * distance_um)  # (e,) grazing angle x lever, µm

    def true_path(z):  # attenuation of a ray crossing at depth z: medium 1, then medium 2
        return jnp.exp(-mu_from_l * (z - z_lo) - mu_to_l * (z_hi - z))

    levers = (distance_um - z_hi, distance_um - z_lo)
    fan = None
    if limits is None and (group.straight_window or group.sub_window):  # the crossing rays over the whole depth
        ends = mass_at(jnp.stack([z_lo, z_hi]))
        fan = jax.lax.stop_gradient((jnp.min(ends.a_min), jnp.max(ends.a_max)))
    straight_aim, straight_spread = aim, lambda values: values
    if group.straight_window and limits is None:  # the straight rays on a sub-window of their own
        start = _covering_start(fan, group.straight_window, aim, levers)
        straight_aim = aim[start + jnp.arange(group.straight_window)]
        straight_spread = _spread(start, group.straight_window, aim.shape[-1])
    z, scale, mass, grazing = nodes(straight_kinks, straight_aim)  # (N, e)
    straight = straight_cumulative(mass, grazing)
    step = jnp.where(z > 0, wavelength_weight @ jnp.exp(-mu_from * depth_um),
                     wavelength_weight @ jnp.exp(-mu_to * depth_um))
    stepped = straight_spread(jnp.sum(step * scale * straight, axis=-2))  # the step assignment of the crossing rays
    attenuation = straight_spread(jnp.sum(jnp.tensordot(wavelength_weight, true_path(z), 1) * scale * straight,
                                          axis=-2)) - stepped
    if not refracting:
        return attenuation, attenuation
    reflected_path = jnp.exp(-mu_from_l * depth_um)
    k_l = k[:, None]
    if rough:  # a leading axis of normal tilts (t, l, 1): nodes (t, l, N, e), sums (t, l, e)
        tilt = slope_rms * _tilt_quantiles(group.rough_strata, k.shape[0])[..., None]
        tilt_weight = np.full(group.rough_strata, 1.0 / group.rough_strata)
        shifted = lambda kinks: lambda m: tuple(angle + tilt for angle in kinks(m))  # local -> global angles
    else:
        tilt = tilt_weight = None
        shifted = lambda kinks: kinks
    samples = k.shape if tilt is None else tilt.shape[:1] + k.shape  # (l,) or (t, l)

    def summed(values):  # over tilts (if rough) and wavelengths: (..., l, e) -> (e,)
        return wavelength_weight @ values if tilt is None else jnp.einsum("t,l,tle->e", tilt_weight,
                                                                          wavelength_weight, values)

    if limits is None:
        deflected = summed(_deflected_rays(group, nodes, true_path, reflected_path, k_l, tilt, shifted, samples, fan,
                                           aim, levers, distance_um))
        return deflected - stepped, attenuation
    # a thin layer's face: reflected up to reflect_k, refracted only up to the outgoing angle limits(z)[2]
    aim_l = jnp.broadcast_to(aim, samples + aim.shape)
    right_of_interface = aim_l > 0.0
    reflect_l, guided_l = restrict[2][:, None], restrict[3][:, None]
    z, scale, mass, grazing = nodes(lambda m: deflected_kinks(m, reflect_l, right_of_interface), aim_l,
                                    deflected=True,
                                    more_cuts=(distance_um + aim_l / jnp.maximum(guided_l, _thin.TINY),))
    refracted, reflected = deflected_cumulative(mass, jnp.minimum(grazing, limits(z)[2]), k_l[..., None],
                                                reflect_l[..., None], guided_l[..., None])
    deflected = summed(jnp.sum((true_path(z) * refracted + reflected_path * reflected) * scale, axis=-2))
    if group.fresnel_nodes:  # rays moved from the refracted to the reflected beam, on nodes of their own kinks
        z, scale, mass, grazing = nodes(lambda m: fresnel_kinks(m, k_l, right_of_interface), aim_l, fresnel=True)
        # rays reflected at a thin layer's second face above ``turn`` cross it back into its A
        w, forward = restrict[:2]
        k_ab, mu_a = (v.reshape(per_lam) for v in restrict[4:6])
        turn = jnp.where(forward, mass.a_max, jnp.maximum(w / jnp.maximum(z_hi - z, _thin.TINY),
                                                          _thin.root(jnp.maximum(-k_ab, 0.0))))
        beyond = _thin.angle_landing_at(aim_l[..., None, :], distance_um - z, w, k_ab, 1, -1, turn, mass.a_max)
        leaves = lambda a: 1.0 - _thin.reflectivity(_thin.root(a * a + k_ab), a)
        below = (aim_l[..., None, :] + 2.0 * w) / (distance_um - z)  # landing a lever - 2 w
        lost, gained, returned = fresnel_transfer(mass, grazing, k_l[..., None], group.fresnel_nodes,
                                                  group.fresnel_weights, (turn, beyond, leaves, below))
        reflected = reflected_path * gained + jnp.exp(-mu_from_l * (z - z_lo) - mu_a * (z_hi - z)) * returned
        deflected = deflected + summed(jnp.sum((reflected - true_path(z) * lost) * scale, axis=-2))
    return deflected - stepped, attenuation


def _deflected_rays(group: ProfileGroup, nodes, true_path, reflected_path, k, tilt, shifted, samples, fan, aim,
                    levers, distance_um):
    """The deflected rays of a face (no thin layer's) landing left of each window edge, per sample
    (..., l, e): refracted, reflected (with Fresnel reflection, partially too) and, on a rough
    face, passing behind its facets; on the depth nodes of ``nodes``, split at the kinks of the
    side of the facet the rays leave on (``landed``). tilt (t, l, 1) rad or None; k (l, 1); aim
    (e,) µm as in ``_crossing_kernel``; fan, levers: as ``_sub_windows``. With the group's
    ``sub_window`` the rays that leave left of the facet's projection and those that leave right
    of it are each evaluated on a sub-window of their own (``_sub_windows``), flat beyond it;
    else both on the whole window."""
    kinks = deflected_and_fresnel_kinks if group.fresnel_nodes else deflected_kinks

    def landed(aim_part, side=None):  # (..., l, e_part)
        """side (e_part,) bool: per edge, only the rays leaving right (True) or left of the facet,
        split at their own kinks (beyond their region every cut then lies at an end of the depth);
        None: all rays, split at the kinks of those leaving on the side of the facet an edge is on."""
        right_of_interface = (aim_part > (0.0 if tilt is None else tilt * distance_um) if side is None
                              else jnp.broadcast_to(side, aim_part.shape))
        z, scale, mass, grazing = nodes(shifted(lambda m: kinks(m, k, right_of_interface)), aim_part, tilt,
                                        mid_plane=not group.fresnel_nodes)  # neither jumps there (``stepped`` does)
        local = grazing if tilt is None else grazing - tilt[..., None]
        cumulative = deflected_cumulative(mass, local, k[..., None], side=side)  # (refracted, reflected) or either
        path = (true_path(z), reflected_path)
        if group.fresnel_nodes:  # rays moved from the refracted to the reflected beam: (lost, gained) or either
            moved = fresnel_transfer(mass, local, k[..., None], group.fresnel_nodes, group.fresnel_weights, side=side)
            cumulative = (cumulative[0] - moved[0], cumulative[1] + moved[1]) if side is None else \
                cumulative + jnp.where(side, -moved, moved)
        if side is None:
            total = path[0] * cumulative[0] + path[1] * cumulative[1]
        else:
            total = jnp.where(side, path[0], path[1]) * cumulative
        if tilt is not None:  # rays that meet their facet from behind pass straight (left of it)
            behind = path[0] * mass.behind(grazing)
            total = total + (behind if side is None else jnp.where(side, 0.0, behind))
        return jnp.sum(total * scale, axis=-2)

    if not group.sub_window:
        return landed(jnp.broadcast_to(aim, samples + aim.shape))
    (left, spread_left), (right, spread_right) = _sub_windows(group.sub_window, fan, 0.0 if tilt is None else tilt,
                                                              k, aim, levers)
    values = landed(jnp.concatenate([left, right], axis=-1), np.arange(sum(group.sub_window)) >= group.sub_window[0])
    return spread_left(values[..., :group.sub_window[0]]) + spread_right(values[..., group.sub_window[0]:])


def _sub_windows(widths: tuple[int, int], fan, tilt, k, aim, levers):
    """Two sub-windows of a side's window per (tilt, wavelength) sample: the edges at which the
    sample's deflected rays leaving left of its facet's projection land, and those of the rays
    leaving right of it (``_kernel.landing_regions``), from every depth.

    widths: their edges (``_plan`` sizes them for the widest); fan: (a_min, a_max) rad, the
    crossing rays' global grazing angles over the whole depth; tilt (t, l, 1) rad or 0; k (l, 1);
    aim (e,) µm, the window's edges as in ``_crossing_kernel``; levers: the shortest and longest
    distance (µm) from the face to the detector. Returns per sub-window its edges' aims (..., width)
    and ``_spread`` from it to the window."""
    regions = jax.lax.stop_gradient(landing_regions(*fan, k, tilt))
    out = []
    for region, width in zip(regions, widths):
        start = _covering_start(region, width, aim, levers)
        out.append((aim[start + jnp.arange(width)], _spread(start, width, aim.shape[-1])))
    return out


def _covering_start(region, width: int, aim, levers):
    """First window edge (int, (...)) of a sub-window of ``width`` edges that holds the edges
    at which rays leaving at grazing angles in ``region`` = (lo, hi) rad (each (...)) land from
    every lever in ``levers`` (µm), with an edge to spare each side (``_plan`` sizes the width);
    aim (e,) µm: the window's edges, as in ``_crossing_kernel``."""
    lo, hi = region
    reach = jnp.stack([angle * lever for angle in (lo, hi) for lever in levers])
    first = jnp.floor(jnp.min((reach - aim[0]) / (aim[1] - aim[0]), axis=0)) - 1.0
    return jnp.clip(first, 0, aim.shape[-1] - width).astype(jnp.int32)


def _spread(start, width: int, n: int):
    """values of a cumulative kernel at a sub-window's ``width`` edges (..., width) from window edge
    ``start`` (int, (..., 1) or ()) -> at the window's n edges (..., n). The kernel is flat
    outside the sub-window: each edge takes the value of its nearest edge of the sub-window."""
    take = jnp.clip(jnp.arange(n) - start, 0, width - 1)
    return lambda values: jnp.take_along_axis(values, jnp.broadcast_to(take, values.shape[:-1] + (n,)), axis=-1)


def _tilt_quantiles(n_strata: int, n_lam: int) -> np.ndarray:
    """Standard-normal tilts (n_strata, n_lam) of equal weight: stratum i of wavelength node j at
    probability (i + f_j) / n_strata, the fractions f_j spread over (0, 1) in van der Corput order,
    so that the wavelength sum sees n_strata * n_lam distinct tilts; scaled to unit variance."""
    def van_der_corput(j):
        value, base = 0.0, 0.5
        while j:
            value, j, base = value + base * (j & 1), j >> 1, base / 2
        return value
    fractions = (np.array([van_der_corput(j) for j in range(n_lam)]) + 0.5 / n_lam) % 1.0
    probability = (np.arange(n_strata)[:, None] + fractions[None, :]) / n_strata
    tilts = np.vectorize(statistics.NormalDist().inv_cdf)(probability)
    return tilts / np.sqrt(np.mean(tilts**2))


def largest_tilt(n_strata: int, n_lam: int) -> float:
    """The largest |normal tilt| (RMS slopes) of a rough face's strata (``_tilt_quantiles``); 0 without."""
    return float(np.max(np.abs(_tilt_quantiles(n_strata, n_lam)))) if n_strata else 0.0


def _side_elements(group: ProfileGroup) -> int:
    """Kernel array elements of one crossing side: window (or sub-window) edges x wavelength
    nodes x depth nodes x strata of a rough face's normal tilt."""
    edges = sum(group.sub_window) if group.sub_window else 2 * group.window + 1
    return edges * group.wavelength_A.shape[1] * len(group.z_nodes) * max(1, group.rough_strata)


def _per_chunk(n: int, elements_each: int) -> int:
    """How many of n items (a group's profiles, a profile's crossing sides) of
    ``elements_each`` kernel array elements are evaluated at once (vmap), the rest in turn.

    On an accelerator all of them. On a CPU as many as keep a chunk within
    ``_CPU_CHUNK_ELEMENTS``: larger buffers are mapped and zeroed afresh by the C allocator
    on every call (the joint fit of 10 BOA distances and 4 ICON lines: 5.9 M page faults and
    10.8 s of solving with its far distances vmapped, 0.2 M and 5.2-6.6 s in turn; the
    five-layer oxide with 2 mrad rough faces: 1.6 GB of buffers an evaluation with its 12
    sides vmapped).
    """
    if jax.default_backend() != "cpu":
        return n
    return max(1, min(n, _CPU_CHUNK_ELEMENTS // max(elements_each, 1)))


def _in_chunks(one, args, chunk: int, needed=None):
    """``one`` (one item's args -> arrays) over the leading axis of args, ``chunk`` items
    at a time: a scan over chunks of a vmap, one traced body whatever the count. The items
    are padded with copies of the last to whole chunks, their results dropped.

    needed (n,) bool, optional: the results of the items not needed are zeros, and a chunk
    without a needed item is not evaluated (``lax.cond``; where all items run at once,
    batched, they are evaluated and then zeroed)."""
    tree_map = jax.tree_util.tree_map
    n = jax.tree_util.tree_leaves(args)[0].shape[0]
    if 1 < n <= chunk:
        out = jax.vmap(one)(args)
        return out if needed is None else _zeroed(out, needed)
    n_chunks = -(-n // chunk)
    chunk = -(-n // n_chunks)  # the fewest padded items for that many chunks
    take = np.minimum(np.arange(n_chunks * chunk), n - 1)
    chunks = tree_map(lambda x: x[take].reshape((n_chunks, chunk) + x.shape[1:]), args)
    keep = None if needed is None else needed[take].reshape(n_chunks, chunk)
    if chunk > 1:
        run = jax.vmap(one)
    else:  # not batched: a lax.cond inside ``one`` skips its other branch too
        run = lambda items: tree_map(lambda x: x[None], one(tree_map(lambda x: x[0], items)))

    def body(items, keep):  # one chunk (chunk, ...) -> its results
        if keep is None:
            return run(items)
        shapes = jax.eval_shape(run, items)
        return jax.lax.cond(jnp.any(keep), lambda a: _zeroed(run(a), keep),
                            lambda a: tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes), items)

    if n_chunks == 1:
        out = tree_map(lambda x: x[None], body(*tree_map(lambda x: x[0], (chunks, keep))))
    else:
        out = jax.lax.map(lambda c: body(*c), (chunks, keep))
    return tree_map(lambda x: x.reshape((n_chunks * chunk,) + x.shape[2:])[:n], out)


def _zeroed(out, keep):
    """The results ``out`` (each (n, ...)) with the rows where ``keep`` (n,) is False zeroed."""
    return jax.tree_util.tree_map(lambda x: jnp.where(keep.reshape(keep.shape + (1,) * (x.ndim - 1)), x, 0), out)


def _profile(group: ProfileGroup, model: ForwardModel, params: ModelParams, distance_mm, shift_um,
             first_edge_um, spectrum, step_spectrum):
    """(T, T_att) bin averages (n_edges-1,) on the padded sub-pixel grid of one profile.

    spectrum, step_spectrum: (wavelengths Å, weights, tabulated mu 1/m) for the kernels
    and, finer, for the plateaus of the step profile.
    """
    wavelength_A, wavelength_weight, mu_table_per_m = spectrum
    distance_um, depth_um = distance_mm * 1e3, params.depth_mm * 1e3
    sld, mu, sld_end, mu_end = _media(params, wavelength_A, mu_table_per_m, model.graded, model.vanishing)
    boundary, slope, z_mid = _boundaries(params, shift_um)
    plane = _assignment_planes(model, z_mid, depth_um)
    edges = first_edge_um + group.bin_um * jnp.arange(group.n_edges)
    positions, planes, jumps, shifts = _step_jumps(model, params, boundary + slope * plane, plane, step_spectrum,
                                                   depth_um, distance_um)
    T = _step_profile(group, positions, jumps, distance_um - planes, edges, shifts)
    T_att = T if shifts is None else _step_profile(group, positions, jumps, distance_um - planes, edges)
    delta_per_sld = wavelength_A**2 * 1e-6 / (2 * jnp.pi)
    slope_rms = 1e-3 * jnp.concatenate([params.left_roughness_mrad[None], params.roughness_mrad])
    if model.thin:
        T, T_att = _thin_terms(group, model.thin, (T, T_att), sld, mu, (boundary, slope, z_mid, plane), distance_um,
                               wavelength_weight, depth_um, delta_per_sld, first_edge_um)
    for refracting, rough in ((True, False), (True, True), (False, False)):
        faces = [f for f in model.interfaces if f.refracting == refracting and f.rough == rough]
        if not faces:
            continue
        # Each face twice: crossing left to right (sign +1) and right to left (-1, mirrored),
        # from the right-hand values of the medium on its left to the left-hand ones on its right.
        sign = jnp.asarray(np.repeat([[1.0, -1.0]], len(faces), axis=0).ravel(), boundary.dtype)
        position = np.repeat([f.position for f in faces], 2)
        left, right = np.asarray([f.left for f in faces]), np.asarray([f.right for f in faces])
        interleave = lambda first, second: jnp.stack([first, second], axis=-1).reshape(first.shape[:-1] + (-1,))
        sld_before, sld_after = interleave(sld_end[left], sld[right]), interleave(sld[right], sld_end[left])
        mu_before = interleave(mu_end[:, left], mu[:, right])
        mu_after = interleave(mu[:, right], mu_end[:, left])
        b = boundary[position]
        landing_um = _landing_centre_um(group, *jax.lax.stop_gradient(
            (b, slope, z_mid[position], 2.0 * (sld_after - sld_before) * jnp.max(delta_per_sld))), sign, distance_um,
            jax.lax.stop_gradient(largest_tilt(group.rough_strata, len(wavelength_weight)) * slope_rms[position])
            if rough else None)
        sides = (sign * b, sign * slope, z_mid[position], mu_before.T, mu_after.T,
                 2.0 * (sld_after - sld_before)[:, None] * delta_per_sld, slope_rms[position], plane[position])
        one_side = functools.partial(_crossing_kernel, group, distance_um=distance_um,
                                     wavelength_weight=wavelength_weight, depth_um=depth_um,
                                     refracting=refracting, rough=rough)
        chunk = _per_chunk(len(position), _side_elements(group))
        dT, dT_att = _windowed(group, first_edge_um, T.shape[0], sign, landing_um, lambda window_edges: _in_chunks(
            lambda a: one_side(a[0], edges_um=a[1]), (sides, window_edges), chunk,
            _reaching(group, first_edge_um, landing_um)))
        T, T_att = T + dT, T_att + dT_att
    return T, T_att


def _windowed(group: ProfileGroup, first_edge_um, n_bins: int, sign, landing_um, cumulative):
    """Bin contributions (n_bins,) to (T, T_att) of kernels evaluated on windows around their landing.

    sign, landing_um: per side (n_side,); cumulative: local-frame window edges (n_side, 2 window + 1)
    µm -> cumulative kernels (C_T, C_att) on them, each (n_side, 2 window + 1).
    """
    n_window = 2 * group.window + 1
    centre = jnp.round(_landing_bin(group, first_edge_um, landing_um)).astype(jnp.int32)
    start = jnp.clip(centre - group.window, 0, group.n_edges - n_window)
    window_edges = first_edge_um + group.bin_um * (start[:, None] + jnp.arange(n_window))
    C_T, C_att = cumulative(sign[:, None] * window_edges)
    scale = sign[:, None] / group.bin_um
    return (_place(scale * jnp.diff(C_T, axis=1), start, n_bins),
            _place(scale * jnp.diff(C_att, axis=1), start, n_bins))


class _ThinFace(NamedTuple):
    """One face of a coupled thin layer B between A and C, in one crossing direction."""

    sign: float  # +1 rays cross it left to right, -1 mirrored
    boundary: int  # its boundary index
    before: int  # the media on either side (indices as in ``Interface``)
    after: int
    width_um: Array  # B's width
    forward: bool  # the first face the rays meet (else the second)
    reflect_k: Array  # (n_lam,) as in ``_thin.face_limits``
    guided_rad: Array  # (n_lam,) below it rays of B are guided (0 for the first face)
    outer: int  # A, the medium the rays come from
    inner: int  # B


def _thin_terms(group: ProfileGroup, thin, values, sld, mu, geometry, distance_um, wavelength_weight,
                depth_um, delta_per_sld, first_edge_um):
    """(T, T_att) plus the kernels of the coupled thin layers (``_thin``).

    Per layer B between A and C and per direction (A -> C, and mirrored C -> A): the
    first face restricted to rays that stay in B, the second restricted to rays that
    started in B (both ``_crossing_kernel``), and the rays through both faces.
    """
    boundary, slope, z_mid, plane = geometry
    T, T_att = values
    group = dataclasses.replace(group, z_nodes=group.thin_z_nodes, z_weights=group.thin_z_weights)
    k = lambda before, after: 2.0 * (sld[np.asarray(after)] - sld[np.asarray(before)])[:, None] * delta_per_sld  # (n, l)
    faces, through = [], []
    for layer in thin:
        w = boundary[layer.layer] - boundary[layer.layer - 1]
        for sign, first, second, (a, b, c) in ((1.0, layer.layer - 1, layer.layer, (layer.left, layer.layer, layer.right)),
                                               (-1.0, layer.layer, layer.layer - 1, (layer.right, layer.layer, layer.left))):
            trapped = _thin.root(jnp.minimum(k([b], [a]), k([b], [c]))[0])  # guided in B below
            faces += [_ThinFace(sign, first, a, b, w, True, jnp.maximum(k([a], [b]), k([a], [c]))[0], 0.0 * trapped, a, b),
                      _ThinFace(sign, second, b, c, w, False, k([b], [c])[0], trapped, a, b)]
            through.append((sign, first, second, a, b, c, w, trapped))

    sign = jnp.asarray([f.sign for f in faces], boundary.dtype)
    position, before, after, outer, inner = (np.asarray([getattr(f, name) for f in faces])
                                             for name in ("boundary", "before", "after", "outer", "inner"))
    b = boundary[position]
    restrict = (jnp.stack([f.width_um for f in faces]), jnp.asarray([f.forward for f in faces]),
                jnp.stack([f.reflect_k for f in faces]), jnp.stack([f.guided_rad for f in faces]),
                k(outer, inner), mu[:, outer].T)
    landing = _landing_centre_um(group, *jax.lax.stop_gradient(
        (b, slope, z_mid[position], 2.0 * (sld[after] - sld[before]) * jnp.max(delta_per_sld))), sign, distance_um)
    sides = (sign * b, sign * slope, z_mid[position], mu[:, before].T, mu[:, after].T, k(before, after),
             jnp.zeros_like(b), plane[position])  # sharp faces
    face_terms = (sign, landing, sides, restrict)

    sign = jnp.asarray([t[0] for t in through], boundary.dtype)
    first, second, a, b_, c = (np.asarray([t[i] for t in through]) for i in (1, 2, 3, 4, 5))
    landing = _landing_centre_um(group, *jax.lax.stop_gradient(  # they leave from the second face
        (boundary[second], slope, z_mid[first], 2.0 * (sld[c] - sld[a]) * jnp.max(delta_per_sld))), sign, distance_um)
    sides = (sign * boundary[first], sign * slope, z_mid[first], mu[:, a].T, mu[:, b_].T, mu[:, c].T,
             k(a, b_), k(a, c), jnp.stack([t[6] for t in through]), plane[first])
    through_terms = (sign, landing, sides)

    sides = (sign * boundary[first], sign * slope, z_mid[first], mu[:, b_].T, jnp.stack([t[7] for t in through]),
             jnp.stack([t[6] for t in through]), plane[first])
    landing = _landing_centre_um(group, *jax.lax.stop_gradient(
        (0.5 * (boundary[first] + boundary[second]), slope, z_mid[first], 0.0 * sign)), sign, distance_um)
    guided_terms = (sign, landing, sides)

    def place(sign, landing_um, cumulative):
        return _windowed(group, first_edge_um, T.shape[0], sign, landing_um, cumulative)

    def layer_terms(terms):  # one layer's (4 faces, 2 through, 2 guided) -> (dT, dT_att) (n_bins,)
        (sign, landing, sides, restrict), through, guided = terms
        kernel = jax.vmap(_crossing_kernel, in_axes=(None, 0, None, None, None, None, None, 0, 0))
        dT, dT_att = place(sign, landing, lambda edges: kernel(group, sides, distance_um, wavelength_weight,
                                                               depth_um, True, False, edges, restrict))
        sign, landing, sides = through
        kernel = jax.vmap(lambda side, edges: _thin.through_kernel(group, side, distance_um, wavelength_weight,
                                                                   depth_um, edges, _kink_aligned_depths))
        more_T, more_att = place(sign, landing, lambda edges: kernel(sides, edges))
        sign, landing, sides = guided
        kernel = jax.vmap(lambda side, edges: _thin.guided_kernel(group, side, distance_um, wavelength_weight,
                                                                  depth_um, edges))
        guided_T, _ = place(sign, landing, lambda edges: kernel(sides, edges))
        return dT + more_T + guided_T, dT_att + more_att

    # a layer at a time on a CPU, so that a layer none of whose windows reaches the profile is skipped
    per_layer = jax.tree_util.tree_map(lambda x: x.reshape((len(thin), -1) + x.shape[1:]),
                                       (face_terms, through_terms, guided_terms))
    reaching = jnp.any(jnp.concatenate([_reaching(group, first_edge_um, terms[1])
                                        for terms in per_layer], axis=1), axis=1)
    dT, dT_att = _in_chunks(layer_terms, per_layer, 1 if jax.default_backend() == "cpu" else len(thin), reaching)
    return T + jnp.sum(dT, axis=0), T_att + jnp.sum(dT_att, axis=0)


def _reaching(group: ProfileGroup, first_edge_um, landing_um):
    """Whether each kernel window centred at ``landing_um`` (...) overlaps the profile's edges.

    A window entirely beyond them adds nothing: its rays land beyond every edge (evaluated,
    the kernel leaves only the drift of its depth quadrature with the edge there, < 1e-6)."""
    centre = _landing_bin(group, first_edge_um, landing_um)
    return (centre + group.window + 1 >= 0) & (centre - group.window - 1 <= group.n_edges - 1)


def _landing_bin(group: ProfileGroup, first_edge_um, landing_um):
    """Where ``landing_um`` lies on the profile's sub-bin edges (fractional edge index)."""
    return (landing_um - first_edge_um) / group.bin_um


def _landing_centre_um(group: ProfileGroup, b, slope, z_mid, k_longest, sign, distance_um, tilt_max=None):
    """Detector position (µm) at the middle of where the crossing rays of each side land.

    b, z_mid, k_longest, sign: per side (n_side,); the window is centred there, so
    its half-width (``_plan``) need not grow with the tilt. tilt_max (rad, per side, or None):
    a rough face's largest normal tilt (``largest_tilt``).
    """
    to_sample_um = group.aperture_distance_um - distance_um
    lo, hi = landing_range(sign * (b / to_sample_um - slope), 0.5 * group.aperture_um / to_sample_um,
                           k_longest, bool(group.fresnel_nodes), tilt=tilt_max)
    return b + slope * distance_um + sign * 0.5 * (lo + hi) * (distance_um - z_mid)


def _place(windows, starts, n_bins: int):
    """Sum of windows (n_face, w) placed at bins starts (n_face,) of a zero array (n_bins,).

    Dense updates rather than a scatter-add: XLA's CPU scatter is serial and its
    forward-mode derivative costs far more than these few dense adds.
    """
    total = jnp.zeros((n_bins,), windows.dtype)
    for row in range(windows.shape[0]):
        placed = jax.lax.dynamic_update_slice(jnp.zeros((n_bins,), windows.dtype), windows[row], (starts[row],))
        total = total + placed
    return total


def _blur_and_bin(group: ProfileGroup, values):
    """Gaussian detector blur, crop of the padding, and sub-bins averaged into pixels."""
    if group.n_pad:
        offsets = np.arange(-group.n_pad, group.n_pad + 1)[:, None] + np.array([-0.5, 0.5])
        cdf = jax.scipy.stats.norm.cdf(offsets * group.bin_um / group.psf_sigma_um)
        kernel = cdf[:, 1] - cdf[:, 0]
        values = jnp.convolve(values, kernel / kernel.sum(), mode="valid")
    return values.reshape(-1, group.n_sub).mean(axis=1)

"""The cylinder's forward model: T(x) and T_att(x) of concentric shells, axis along the columns.

Rays from the aperture's centre at impact parameters b (µm from the axis, both signs, one
trace for |b|) are traced exactly through the circles (``_rays``) at each wavelength node.
A ray through the sample plane at x = centre + b lands on the detector at
X = M (centre + b) + Delta eps(|b|) sign(b), M = L / (L - Delta) (L: aperture to detector,
Delta: axis to detector); a ray from elsewhere on the aperture meets the sample under a
small angle, which the cylinder's symmetry leaves without effect on eps, and lands
shifted by the aperture point x Delta / (L - Delta): the penumbra, of width
w = D Delta / (L - Delta), convolves the landings with the aperture's x-marginal.

The rays are a quadrature in b: a uniform grid, and beside every circle a geometric
grid (1e-5 µm to a few µm from it, both sides) for the grazing, totally reflected and just
refracted rays whose deflection changes like sqrt(distance to the circle); the two are
joined by a partition of unity (a cos^2 taper over the last three quarters of the fine grid's
reach, which spans four steps of the uniform grid, so that the uniform grid resolves it), so every ray's
weight moves with the radii. Each ray's weight (spectrum weight x exp(-depth) x its
width in b) is deposited on a grid of sub-pixel cells by cloud-in-cell, minus the
same ray undeviated and unattenuated (so the open beam, and every ray beyond the sample,
adds exactly nothing, whatever part of the sample the profile shows); with Fresnel partial
reflection (the group's ``fresnel``) each ray is its reflected and unreflected branches
(``_rays.fresnel_trace``), each deposited so, the undeviated ray subtracted once; the cells are
convolved with the penumbra and the detector's Gaussian blur and averaged into pixels.
T_att is exp(-sum mu_k chord_k) at each cell's point of the sample plane (n = 1, straight
chords), on finer wavelength nodes, convolved alike.

Internal units: µm, rad, Å; mu in 1/µm. float64 only (``_rays``).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._aperture import APERTURES
from .._grouped import GroupedModel
from ._rays import chords, fresnel_trace, trace



class CylinderParams(eqx.Module):
    """Traced parameters, in the units of the scene keys.

    outer_radius_um, centre_um: scalars. Per layer (n_layer,), outside in: thickness_um
    (a rod's innermost layer fills the rest of the radius: its entry is not used),
    sld_e6_per_A2, mu_per_m, mu_per_m_per_A, density_scale (multiplies the SLD and the
    whole mu(lambda)). Per profile (n_profile,): distance_mm (axis to detector), shift_um.
    """

    outer_radius_um: Float[Array, ""]
    thickness_um: Float[Array, " layer"]
    sld_e6_per_A2: Float[Array, " layer"]
    mu_per_m: Float[Array, " layer"]
    mu_per_m_per_A: Float[Array, " layer"]
    density_scale: Float[Array, " layer"]
    centre_um: Float[Array, ""]
    distance_mm: Float[Array, " profile"]
    shift_um: Float[Array, " profile"]


class CylinderGroup(eqx.Module):
    """Profiles sharing one static plan (cells, kernel sizes, wavelength nodes), vmapped.

    Each profile's pixels are split into ``n_sub`` cells of ``cell_um``, padded by ``n_pad``
    cells per side for the penumbra (``aperture_cells``) and the blur (``psf_cells``).
    """

    index: tuple[int, ...] = eqx.field(static=True)
    aperture: str = eqx.field(static=True)
    aperture_um: float = eqx.field(static=True)
    aperture_distance_um: float = eqx.field(static=True)
    psf_sigma_um: float = eqx.field(static=True)
    cell_um: float = eqx.field(static=True)
    n_pixel: int = eqx.field(static=True)
    n_sub: int = eqx.field(static=True)
    aperture_cells: int = eqx.field(static=True)
    psf_cells: int = eqx.field(static=True)
    fresnel: bool = eqx.field(static=True)  # Fresnel partial reflection at every circle (``_rays.fresnel_trace``)
    first_cell_um: Float[Array, " group"]  # centre of each profile's first (padding) cell
    wavelength_A: Float[Array, "group lam"]
    wavelength_weight: Float[Array, "group lam"]
    mu_table_per_m: Float[Array, "group lam layer"]
    att_wavelength_A: Float[Array, "group fine"]  # finer nodes for T_att (straight chords cost little)
    att_weight: Float[Array, "group fine"]
    att_mu_table_per_m: Float[Array, "group fine layer"]

    @property
    def n_pad(self) -> int:
        return self.aperture_cells + self.psf_cells


class CylinderModel(GroupedModel):
    """Predicts (T, T_att) for every profile of a cylinder scene; build it with ``build_model``.

    The faces of every geometry's model (``_grouped.GroupedModel``), so that the predictor
    compiles it as the block's."""

    groups: tuple[CylinderGroup, ...]
    coarse_b_um: Float[Array, " coarse"]  # the uniform grid's impact parameters (midpoints)
    coarse_step_um: float = eqx.field(static=True)
    n_profiles: int = eqx.field(static=True)
    fine_d_um: Float[Array, " fine"] = None  # the circles' grids: distances from the circle ...
    fine_weight_um: Float[Array, " fine"] = None  # ... and their quadrature weights x taper
    taper_um: tuple[float, float] = eqx.field(static=True, default=(0.5, 2.0))  # the fine grids' reach
    tube: bool = eqx.field(static=True, default=False)  # a vacuum core inside the innermost layer

    def stacked(self, params: CylinderParams) -> tuple[tuple[Array, Array], ...]:
        """Pixel-averaged (T, T_att) per group, each (n_group_profiles, n_pixel)."""
        out = []
        for group in self.groups:
            index = np.asarray(group.index)
            args = (params.distance_mm[index], params.shift_um[index], group.first_cell_um,
                    (group.wavelength_A, group.wavelength_weight, group.mu_table_per_m),
                    (group.att_wavelength_A, group.att_weight, group.att_mu_table_per_m))
            out.append(jax.vmap(lambda *a: _profile(group, self, params, *a))(*args))
        return tuple(out)

    @staticmethod
    def group_pixels(group) -> int:
        return group.n_pixel


def radii_um(model: CylinderModel, params: CylinderParams):
    """The circles' radii (n_shell + 1,) µm, outside in, ending at the core's centre 0: the
    outer radius minus the layers' thicknesses (a rod's core: to 0; a tube's vacuum core is
    one more shell), clipped at 0."""
    thickness = params.thickness_um if model.tube else params.thickness_um[:-1]
    inside = params.outer_radius_um - jnp.concatenate([jnp.zeros((1,), thickness.dtype), jnp.cumsum(thickness)])
    return jnp.concatenate([jnp.maximum(inside, 0.0), jnp.zeros((1,), thickness.dtype)])


def _media(model: CylinderModel, params: CylinderParams, wavelength_A, mu_table_per_m):
    """SLD (n_shell,) 1e-6 Å^-2 and mu (n_lam, n_shell) 1/µm of every shell (a tube's core: vacuum)."""
    sld = params.density_scale * params.sld_e6_per_A2
    mu = 1e-6 * params.density_scale * (params.mu_per_m + params.mu_per_m_per_A * wavelength_A[:, None]
                                        + mu_table_per_m)
    if model.tube:
        sld, mu = jnp.pad(sld, (0, 1)), jnp.pad(mu, ((0, 0), (0, 1)))
    return sld, mu


def taper(distance_um, taper_um: tuple[float, float]):
    """1 within taper_um[0] of a circle, 0 beyond taper_um[1], cos^2 between (numpy or jax)."""
    near, far = taper_um
    xp = np if isinstance(distance_um, np.ndarray) else jnp
    t = xp.clip((xp.abs(distance_um) - near) / (far - near), 0.0, 1.0)
    return xp.cos(0.5 * np.pi * t) ** 2


def rays(model: CylinderModel, radii):
    """Impact parameters b (N,) µm >= 0 and their weights (N,) µm: the uniform grid tapered
    off near every circle, and the circles' own grids on both sides."""
    circles = radii[:-1]
    near = jnp.sum(taper(model.coarse_b_um[:, None] - circles[None, :], model.taper_um), axis=1)
    fine_b = jnp.concatenate([(circles[:, None] - model.fine_d_um[None, :]).ravel(),
                              (circles[:, None] + model.fine_d_um[None, :]).ravel()])
    fine_w = jnp.tile(model.fine_weight_um, 2 * circles.shape[0])
    b = jnp.concatenate([model.coarse_b_um, fine_b])
    weight = jnp.concatenate([model.coarse_step_um * (1.0 - near), jnp.where(fine_b > 0, fine_w, 0.0)])
    return jnp.maximum(b, 0.0), weight


def _deposit(n_cells: int, first_cell_um, cell_um: float, X, weight):
    """Cloud-in-cell sums (n_cells, ...) of weights (N, ...) at positions X (N,) µm on cells
    centred at first_cell_um + j cell_um; positions beyond the cells are dropped."""
    u = (X - first_cell_um) / cell_um
    i = jnp.floor(u)
    f = (u - i).reshape(u.shape + (1,) * (weight.ndim - 1))
    i = i.astype(jnp.int32)
    out = jnp.zeros((n_cells,) + weight.shape[1:], weight.dtype)
    for offset, share in ((0, 1.0 - f), (1, f)):
        j = i + offset
        j = jnp.where((j >= 0) & (j < n_cells), j, n_cells)  # out of range: dropped
        out = out.at[j].add(weight * share, mode="drop")
    return out


def _kernel(group: CylinderGroup, width_um):
    """The penumbra (width_um wide, the aperture's x-marginal) convolved with the detector
    blur, as cell masses (2 n_pad + 1,)."""
    cdf = APERTURES[group.aperture][0]
    m = np.arange(-group.aperture_cells, group.aperture_cells + 1)
    edges = (np.concatenate([m - 0.5, m[-1:] + 0.5]) * group.cell_um)
    kernel = jnp.diff(cdf(2.0 * edges / width_um))
    if group.psf_cells:
        m = np.arange(-group.psf_cells, group.psf_cells + 1)
        edges = np.concatenate([m - 0.5, m[-1:] + 0.5]) * group.cell_um / (group.psf_sigma_um * math.sqrt(2.0))
        gauss = np.diff(0.5 * (1.0 + np.vectorize(math.erf)(edges)))
        kernel = jnp.convolve(kernel, jnp.asarray(gauss / gauss.sum()), mode="full")
    return kernel


def _profile(group: CylinderGroup, model: CylinderModel, params: CylinderParams, distance_mm, shift_um,
             first_cell_um, spectrum, att_spectrum):
    """(T, T_att) pixel averages (n_pixel,) of one profile."""
    L, distance_um = group.aperture_distance_um, 1e3 * distance_mm
    magnification = L / (L - distance_um)
    centre = params.centre_um + shift_um
    radii = radii_um(model, params)
    b, width = rays(model, radii)
    wavelength_A, wavelength_weight, table = spectrum
    sld, mu = _media(model, params, wavelength_A, table)
    index = jnp.sqrt(1.0 - wavelength_A[:, None] ** 2 * sld[None, :] * 1e-6 / jnp.pi)  # (l, S)
    weight = wavelength_weight[:, None] * width[None, :]  # (l, N)
    if group.fresnel:  # (l, N, branches)
        eps, depth, share = jax.vmap(lambda n, m: fresnel_trace(b, radii, n, m))(index, mu)
        flux = weight[..., None] * share * jnp.exp(-depth)
        along = lambda values: values[:, None]
    else:  # (l, N)
        eps, depth = jax.vmap(lambda n, m: trace(b, radii, n, m))(index, mu)
        flux = weight * jnp.exp(-depth)
        along = lambda values: values
    straight = magnification * centre + magnification * b  # the +b side; -b mirrored
    n_cells = group.n_pixel * group.n_sub + 2 * group.n_pad
    mirrored = magnification * centre - magnification * b
    landing = jnp.concatenate([(along(straight) + distance_um * eps).ravel(),
                               (along(mirrored) - distance_um * eps).ravel()])
    deposit = _deposit(n_cells, first_cell_um, group.cell_um, landing, jnp.concatenate([flux.ravel()] * 2))
    undeviated = jnp.concatenate([straight, mirrored])
    reference = _deposit(n_cells, first_cell_um, group.cell_um, undeviated, jnp.concatenate([-width] * 2))
    # T_att at the cells themselves (straight chords through the points the cells see): no
    # ray quadrature, whose weights near a circle would not cancel as T's do
    att_lam, att_weight, att_table = att_spectrum
    _, att_mu = _media(model, params, att_lam, att_table)
    seen = jnp.abs((first_cell_um + group.cell_um * jnp.arange(n_cells)) / magnification - centre)
    attenuated = att_weight @ jnp.exp(-att_mu @ chords(seen, radii).T)  # (n_cells,)
    change = jnp.stack([magnification / group.cell_um * (deposit + reference), attenuated - 1.0])
    kernel = _kernel(group, group.aperture_um * distance_um / (L - distance_um))
    blurred = jax.vmap(lambda cells: jnp.convolve(cells, kernel, mode="valid"))(change)
    T, T_att = 1.0 + blurred.reshape(2, group.n_pixel, group.n_sub).mean(axis=-1)
    return T, T_att

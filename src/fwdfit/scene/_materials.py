"""Neutron constants of a layer's material: coherent SLD and attenuation mu(lambda).

Constants come from ``periodictable`` (formula + density) or, for polycrystals
with Bragg edges, from NCrystal (optional extra). Nothing is hand-tabulated.

Attenuation model (per metre): ``mu(lambda) = mu_per_m + mu_per_m_per_A * lambda[Å]
+ mu_table(lambda)``. From a formula, ``mu_per_m`` is the free-atom coherent plus
incoherent scattering (counted as a loss, as McStas' Refractor does: no Bragg
edges) and ``mu_per_m_per_A`` the 1/v absorption, tabulated at 1.798 Å.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from .._errors import FwdfitError

THERMAL_WAVELENGTH_A = 1.798  # wavelength at which absorption cross-sections are tabulated
_MIN_EDGE_A = 0.1  # Bragg edges below this wavelength are not listed
_EDGE_SIDE_REL = 1e-9  # relative offset at which mu is read on either side of an edge


@dataclasses.dataclass(frozen=True)
class MaterialConstants:
    """Optical constants of one material.

    sld_e6_per_A2: coherent scattering length density, 1e-6 Å^-2.
    mu_per_m, mu_per_m_per_A: attenuation ``mu_per_m + mu_per_m_per_A * lambda[Å]``, 1/m.
    mu_table: optional extra attenuation ``lambda_A -> 1/m`` (NCrystal Bragg edges).
    ncrystal_cfg: the NCrystal cfg string the constants came from (kept for writing scenes).
    formula, density_g_cm3: the formula and density (g/cm^3) they came from, if any (likewise).
    bragg_edges_A, bragg_jumps_per_m: wavelengths (Å, decreasing) where ``mu_table`` jumps,
    and mu just below minus just above each (1/m).
    """

    sld_e6_per_A2: float
    mu_per_m: float
    mu_per_m_per_A: float = 0.0
    mu_table: Callable[[np.ndarray], np.ndarray] | None = dataclasses.field(default=None, compare=False)
    ncrystal_cfg: str | None = None
    bragg_edges_A: tuple[float, ...] = ()
    bragg_jumps_per_m: tuple[float, ...] = ()
    formula: str | None = None
    density_g_cm3: float | None = None


def constants_from_formula(formula: str, density_g_cm3: float) -> MaterialConstants:
    """Coherent SLD, scattering loss and 1/v absorption of a compound via periodictable."""
    import periodictable
    from periodictable import nsf

    try:
        compound = periodictable.formula(formula)
    except Exception as error:  # periodictable raises several parser exception types
        raise FwdfitError(f"unknown material {formula!r}: {error}") from None
    if not compound.atoms:
        raise FwdfitError(f"unknown material {formula!r}: empty formula")
    sld, xs, _ = nsf.neutron_scattering(
        compound, density=density_g_cm3, wavelength=THERMAL_WAVELENGTH_A
    )
    if sld is None:
        raise FwdfitError(f"material {formula!r}: no neutron constants for one of its elements")
    coherent_per_cm, absorption_per_cm, incoherent_per_cm = (float(v) for v in xs)
    return MaterialConstants(
        sld_e6_per_A2=float(sld[0]),
        mu_per_m=100.0 * (coherent_per_cm + incoherent_per_cm),
        mu_per_m_per_A=100.0 * absorption_per_cm / THERMAL_WAVELENGTH_A,
        formula=formula,
        density_g_cm3=float(density_g_cm3),
    )


def constants_from_ncrystal(cfg: str) -> MaterialConstants:
    """SLD and attenuation (Bragg edges included) of an NCrystal cfg string (``"Al_sg225.ncmat;temp=200K"``).

    SLD: coherent scattering lengths times number density. mu(lambda): NCrystal's total
    scattering plus absorption cross-sections times number density, as ``mu_table``.
    ``bragg_edges_A``: every edge (lambda = 2 d of a plane family) above 0.1 Å, with the
    drop in mu across it in ``bragg_jumps_per_m``, for the spectrum quadrature.
    """
    try:
        import NCrystal
    except ImportError:
        raise FwdfitError(
            f"material {cfg!r} needs NCrystal: pip install 'fwdfit[ncrystal]'"
        ) from None
    try:
        info = NCrystal.createInfo(cfg)
        scatter = NCrystal.createScatter(cfg)
        absorb = NCrystal.createAbsorption(cfg)
    except Exception as error:  # NCrystal raises its own exception hierarchy
        message = " ".join(str(error).split())
        raise FwdfitError(f"NCrystal material {cfg!r}: {message}") from None
    per_m_per_barn = 100.0 * info.getNumberDensity()  # (atoms/Å^3) x barn = 1/cm
    sld_e6 = 1e6 * info.getNumberDensity() * 1e-5 * sum(
        fraction * atom.coherentScatLenFM() for fraction, atom in info.composition
    )  # 1 fm = 1e-5 Å

    def mu_table(wavelength_A: np.ndarray) -> np.ndarray:
        energy = NCrystal.wl2ekin(np.asarray(wavelength_A, dtype=float))
        barn = scatter.crossSectionIsotropic(energy) + absorb.crossSectionIsotropic(energy)
        return per_m_per_barn * np.asarray(barn, dtype=float)

    edges = np.unique([2.0 * hkl.d for hkl in info.hklObjects()]) if info.hasHKLInfo() else np.zeros(0)
    edges = edges[edges > _MIN_EDGE_A][::-1]
    jumps = mu_table(edges * (1 - _EDGE_SIDE_REL)) - mu_table(edges * (1 + _EDGE_SIDE_REL))
    return MaterialConstants(sld_e6_per_A2=sld_e6, mu_per_m=0.0, mu_table=mu_table, ncrystal_cfg=cfg,
                             bragg_edges_A=tuple(float(v) for v in edges),
                             bragg_jumps_per_m=tuple(float(v) for v in jumps))

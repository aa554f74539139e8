"""What every geometry's forward model shares: its profiles run in groups (one static plan
each, vmapped), and the groups' rows are put back in the scene's order.

A model subclasses ``GroupedModel`` and gives ``stacked`` (the groups' pixel-averaged
(T, T_att), each (n_group_profiles, n_pixel)) and ``group_pixels``; the predictor, the
objective and the fitter use ``grouped``, ``flat``, ``scene_order`` and ``__call__``.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array


class GroupedModel(eqx.Module):
    """A forward model whose profiles run in ``groups`` (each with its ``index`` of scene profiles)."""

    groups: eqx.AbstractVar[tuple]
    n_profiles: eqx.AbstractVar[int]

    @abc.abstractmethod
    def stacked(self, params) -> tuple[tuple[Array, Array], ...]:
        """Pixel-averaged (T, T_att) per group, each (n_group_profiles, n_pixel), rows in
        ``group.index`` order."""

    @staticmethod
    @abc.abstractmethod
    def group_pixels(group) -> int:
        """Pixels of each profile of ``group``."""

    def grouped(self, params, norm=None, background=None) -> tuple[tuple[Array, Array], ...]:
        """(T, T_att) per group, each (n_group_profiles * n_pixel,): the group's profiles in
        ``group.index`` order, ``norm * T + background`` when given (per profile of the scene,
        (n_profile,))."""
        out = []
        for group, (T_g, T_att_g) in zip(self.groups, self.stacked(params)):
            index = np.asarray(group.index)
            n = 1.0 if norm is None else norm[index][:, None]
            b = 0.0 if background is None else background[index][:, None]
            out.append(((n * T_g + b).ravel(), (n * T_att_g + b).ravel()))
        return tuple(out)

    def flat(self, params, norm=None, background=None) -> tuple[Array, Array]:
        """(T, T_att) of every profile's pixels concatenated in scene order (n_pixel_total,),
        ``norm * T + background`` when given (per profile, (n_profile,)); one gather, not one
        op per profile."""
        parts = self.grouped(params, norm, background)
        T, T_att = (jnp.concatenate([part[k] for part in parts]) for k in (0, 1))
        order = self.scene_order
        return (T, T_att) if order is None else (T[order], T_att[order])

    @property
    def scene_order(self) -> np.ndarray | None:
        """Static gather from group order to scene order of the flat pixels; None if the same."""
        starts, sizes, position = {}, {}, 0
        for group in self.groups:
            n_pixel = self.group_pixels(group)
            for i in group.index:
                starts[i], sizes[i] = position, n_pixel
                position += n_pixel
        order = np.concatenate([np.arange(starts[i], starts[i] + sizes[i]) for i in range(self.n_profiles)])
        return None if np.array_equal(order, np.arange(position)) else order

    def __call__(self, params) -> tuple[list[Array], list[Array]]:
        """Pixel-averaged T and T_att, one array (n_pixel,) per profile, in scene order."""
        T: list = [None] * self.n_profiles
        T_att: list = [None] * self.n_profiles
        for group, (T_g, T_att_g) in zip(self.groups, self.stacked(params)):
            for row, i in enumerate(group.index):
                T[i], T_att[i] = T_g[row], T_att_g[row]
        return T, T_att

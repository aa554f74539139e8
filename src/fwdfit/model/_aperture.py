"""Aperture x-marginals in the normalised coordinate v = 2 x_ap / D in [-1, 1].

For each shape: the density rho(v), its CDF ``cdf(v)``, first moment
``moment(v) = int_{-1}^{v} rho(u) u du`` and ``cdf_integral(s) = int_{-inf}^{s} cdf``
(continued linearly beyond the rim). All are pure JAX functions, finite with
finite gradients everywhere including the rim |v| = 1.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def _unit(v):
    return jnp.clip(v, -1.0, 1.0)


def _square_cdf(v):
    return 0.5 * (_unit(v) + 1.0)


def _square_moment(v):
    return 0.25 * (_unit(v) ** 2 - 1.0)


def _square_cdf_integral(s):
    inside = 0.25 * (_unit(s) + 1.0) ** 2
    return jnp.where(s > 1.0, s, inside)


def _sqrt_one_minus_square(v):
    return jnp.sqrt(jnp.maximum(1.0 - v * v, 0.0))


@jax.custom_jvp
def _circle_cdf(v):
    v = _unit(v)
    return 0.5 + (v * _sqrt_one_minus_square(v) + jnp.arcsin(v)) / jnp.pi


def _circle_density(v):
    return jnp.where(jnp.abs(v) < 1.0, 2.0 / jnp.pi * _sqrt_one_minus_square(v), 0.0)


@_circle_cdf.defjvp
def _circle_cdf_jvp(primals, tangents):
    (v,), (dv,) = primals, tangents
    return _circle_cdf(v), _circle_density(v) * dv


@jax.custom_jvp
def _circle_moment(v):
    root = _sqrt_one_minus_square(_unit(v))  # as in the CDF, so XLA computes it once
    return -2.0 / (3.0 * jnp.pi) * root * root * root


@_circle_moment.defjvp
def _circle_moment_jvp(primals, tangents):
    (v,), (dv,) = primals, tangents
    return _circle_moment(v), _circle_density(v) * v * dv


@jax.custom_jvp
def _circle_cdf_integral(s):
    u = _unit(s)
    root = _sqrt_one_minus_square(u)
    inside = 0.5 * u + (-(root**3) / 3.0 + u * jnp.arcsin(u) + root) / jnp.pi
    return jnp.where(s > 1.0, s, inside)


@_circle_cdf_integral.defjvp
def _circle_cdf_integral_jvp(primals, tangents):
    (s,), (ds,) = primals, tangents
    return _circle_cdf_integral(s), _circle_cdf(s) * ds


APERTURES = {
    "square": (_square_cdf, _square_moment, _square_cdf_integral),
    "circular": (_circle_cdf, _circle_moment, _circle_cdf_integral),
}

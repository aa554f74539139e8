"""Host values to device arrays, shared by every geometry's parameters."""

from __future__ import annotations

import jax
import numpy as np


def to_device(values, dtype=None):
    """values as a JAX array of ``dtype`` (default float, float32 without x64): a plain
    transfer, where ``jnp.asarray`` compiles a small program for every new shape (~14 ms
    each, ~0.2 s of a warm run's plan)."""
    return jax.device_put(np.asarray(values, dtype=float if dtype is None else dtype))

"""Shared test setup: float64 by default, a float32 switch, and the reference-data loader.

float64 is what fitting uses, so it is the default for every test. ``float32`` gives a
context manager in which JAX creates and computes in single precision (``jax.enable_x64``
in JAX 0.10; build the model inside it, so that its arrays are float32 too).
"""

import contextlib

import jax
import pytest

jax.config.update("jax_enable_x64", True)

from helpers import DATA, load_reference  # noqa: E402  (after the float64 switch)

__all__ = ["DATA", "load_reference"]


@contextlib.contextmanager
def _precision(x64: bool):
    with jax.enable_x64(x64):
        yield


@pytest.fixture
def float32():
    """``with float32(): ...`` runs its body with 64-bit types disabled."""
    return lambda: _precision(False)


@pytest.fixture(params=["float64", "float32"])
def precision(request):
    """Each test using it runs twice: ``(name, context manager factory)``."""
    return request.param, (lambda: _precision(request.param == "float64"))


@pytest.fixture(scope="session")
def reference_loader():
    """``load_reference(case_dir, name)``: x_um, T, T_err, T_att, T_att_err of a reference."""
    return load_reference

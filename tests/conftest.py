"""Shared test setup: float64 by default and a ``float32`` fixture.

float64 is what fitting uses, so every test runs in it unless it asks for ``float32``,
which runs the test body with 64-bit types disabled (``jax.enable_x64(False)``, the
context manager of JAX 0.10; build the model inside it so that its arrays are float32
too). Helpers shared by the test files (reference loading, scenes written on the fly,
edge metrics, brute-force references) live in ``helpers.py``.
"""

import os
import tempfile

import jax
import pytest

import fwdfit

# XLA's CPU compiler without its newer fusion emitters compiles these models 25-40 % faster
# (reverse-mode programs most) and evaluates them up to 20 % slower: the trade a test suite
# of many short-lived programs wants, not the fits of a user (the library leaves the default).
# Set before JAX's backend starts; CLI subprocesses of the tests inherit it.
if "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_use_fusion_emitters=false").strip()
jax.config.update("jax_enable_x64", True)
# Compiled programs of this session go to a fresh folder, never the user's cache: one folder
# for the whole session, made by the first process that loads this file (pytest-xdist's
# workers inherit it from the controller), so a program one worker compiled the other loads.
if not os.environ.get("FWDFIT_TEST_SESSION_CACHE"):
    os.environ["FWDFIT_TEST_SESSION_CACHE"] = tempfile.mkdtemp(prefix="fwdfit-test-cache-")
os.environ["FWDFIT_CACHE_DIR"] = os.environ["FWDFIT_TEST_SESSION_CACHE"]
# JAX's persistent cache in that folder too: a test that builds a model another test (or
# worker, or CLI subprocess) compiled already loads the program instead of compiling it.
fwdfit.enable_compilation_cache()


@pytest.fixture
def float32():
    """Run the test body in single precision."""
    with jax.enable_x64(False):
        yield

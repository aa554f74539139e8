"""Run every notebook in ``notebooks/`` top to bottom, as a user would; fail on any error.

Each notebook is executed in memory by nbclient (kernel ``python3``, working directory
``notebooks/``, a time limit per cell); the file on disk is not touched. The notebooks
check real numbers themselves with ``assert`` (fitted thickness, tilt and attenuation
against the references, the Paganin filter's best b, ...), so an error in any cell,
assertions included, fails the test.

The kernels import the same fwdfit as this test session (its folder goes first on
their PYTHONPATH) and share the test session's compilation cache folder: fits that
two notebooks (or a notebook and a test) compile identically (01 and 02, 03 and 04)
are compiled once. Runtime on two CPU cores: a few minutes for all eight, most of it the
fits' compilation (marked slow; ``-m "not slow"`` leaves them out).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

import fwdfit

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
NAMES = sorted(path.name for path in NOTEBOOKS.glob("*.ipynb"))
CELL_TIMEOUT_S = 600


@pytest.fixture(scope="module")
def kernel_env():
    """Environment of the notebook kernels: this session's fwdfit, and the session's
    compilation cache (``conftest.py``) for JAX's programs as for fwdfit's."""
    package_root = str(Path(fwdfit.__file__).resolve().parents[1])
    python_path = os.pathsep.join(p for p in (package_root, os.environ.get("PYTHONPATH")) if p)
    return dict(os.environ, PYTHONPATH=python_path, JAX_COMPILATION_CACHE_DIR=os.environ["FWDFIT_CACHE_DIR"])


def test_notebooks_found():
    assert NAMES == ["01_quick_start.ipynb", "02_al_block.ipynb", "03_oxide.ipynb",
                     "04_paganin_vs_forward_model.ipynb", "05_speed_vs_error.ipynb",
                     "06_time_of_flight.ipynb", "07_graded_rough_coating.ipynb",
                     "08_cladding_tube.ipynb"]


@pytest.mark.slow
@pytest.mark.parametrize("name", NAMES)
def test_notebook_runs(name, kernel_env):
    notebook = nbformat.read(NOTEBOOKS / name, as_version=4)
    client = nbclient.NotebookClient(notebook, timeout=CELL_TIMEOUT_S, kernel_name="python3",
                                     resources={"metadata": {"path": str(NOTEBOOKS)}})
    start = time.perf_counter()
    client.execute(env=kernel_env)  # raises CellExecutionError, naming the cell, on any error
    print(f"{name}: {time.perf_counter() - start:.0f} s")
    errors = [output for cell in notebook.cells if cell.cell_type == "code"
              for output in cell.get("outputs", []) if output.get("output_type") == "error"]
    assert not errors

"""Where benchmark results go (benchmarks/results/, or benchmarks/results/quick/ for --quick
runs), and the machine record that goes with them."""

import os
import platform
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def results_dir(quick: bool) -> Path:
    """The folder for a run's JSON, Markdown and PNG results (created)."""
    folder = ROOT / "benchmarks" / "results" / ("quick" if quick else "")
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def machine_record() -> dict:
    """The machine and versions a result was measured with."""
    import jax

    return {"cpus": os.cpu_count(), "platform": platform.platform(), "device": str(jax.devices()[0]),
            "jax": jax.__version__, "python": platform.python_version()}

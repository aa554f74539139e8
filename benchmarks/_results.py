"""Where benchmark results go (benchmarks/results/, or benchmarks/results/quick/ for --quick
runs), the machine record that goes with them, and the plain command timed as a user runs it."""

import json
import os
import platform
import subprocess
import sys
import time
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


def run_command(scene: Path, out: Path, cache: Path) -> dict:
    """``fwdfit fit SCENE --out OUT`` in a fresh process with the compilation cache in
    ``cache`` (empty: cold; filled by an earlier run: warm): wall time, exit status and
    what result.json says."""
    start = time.perf_counter()
    env = {**os.environ, "FWDFIT_CACHE_DIR": str(cache)}
    run = subprocess.run([sys.executable, "-m", "fwdfit.cli", "fit", str(scene), "--out", str(out), "--quiet"],
                         env=env, capture_output=True, text=True)
    wall = time.perf_counter() - start
    result = json.loads((out / "result.json").read_text())
    return {"status": run.returncode, "wall_s": round(wall, 2), "compile_s": round(result["compile_time_s"], 2),
            "solve_s": round(result["solve_time_s"], 2), "chi2": result["chi2"],
            "chi2_reduced": round(result["chi2_reduced"], 4), "accepted": result["accepted"],
            "values": {k: v["value"] for k, v in result["parameters"].items()}}


def write_result(name: str, record: dict, quick: bool) -> Path:
    """Write ``record`` as ``<results>/<name>.json`` (``results_dir``) and say where."""
    path = results_dir(quick) / f"{name}.json"
    path.write_text(json.dumps(record, indent=2) + "\n")
    print(f"wrote {path}")
    return path

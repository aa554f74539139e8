"""Where benchmark results go: benchmarks/results/, or benchmarks/results/quick/ for --quick runs."""

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def results_dir(quick: bool) -> Path:
    """The folder for a run's JSON, Markdown and PNG results (created)."""
    folder = ROOT / "benchmarks" / "results" / ("quick" if quick else "")
    folder.mkdir(parents=True, exist_ok=True)
    return folder

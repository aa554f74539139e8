"""How often does a single start reach the best fit? The multistart check over several draws.

``tests/test_multistart.py`` checks one draw of data and starts per sample (the Al
block, five free values; the five-layer oxide, nine free values). This script runs
the test's own setup (its scenes, bounds, noise and uniform starts inside the
bounds) for several seeds, each seed a new draw of both the noise and the 20
starts, and records for each how many starts end within delta chi2 < 0.5 of the
best, and the delta chi2 of the others.

    python benchmarks/multistart.py [--quick]

Writes ``benchmarks/results/multistart.json`` (``--quick``: one Al seed).
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import test_multistart as case  # noqa: E402

from _results import machine_record, results_dir  # noqa: E402

SAMPLES = {"al": (case.al_scene, case.AL_TRUTH, case.AL_BOUNDS),
           "oxide": (case.oxide_scene, case.OXIDE_TRUTH, case.OXIDE_BOUNDS)}
SEEDS = {"al": (1, 2, 3), "oxide": (2, 3, 4, 5)}


def main(quick: bool) -> None:
    seeds = {"al": (1,)} if quick else SEEDS
    rows = []
    for sample, sample_seeds in seeds.items():
        scene_text, truth, bounds = SAMPLES[sample]
        for seed in sample_seeds:
            start = time.perf_counter()
            with tempfile.TemporaryDirectory() as folder:
                result, _ = case._multistart(Path(folder), scene_text, truth, bounds, seed)
            delta = np.sort(result.chi2_per_start - result.chi2_per_start.min())
            reached = int(np.sum(delta < case.REACHED_DELTA_CHI2))
            row = {"sample": sample, "seed": seed, "n_free": len(result.names),
                   "starts": case.N_STARTS, "reached": reached,
                   "missed_delta_chi2": [round(float(d), 2) for d in delta[reached:]],
                   "best_chi2_reduced": round(result.chi2_reduced, 4),
                   "time_s": round(time.perf_counter() - start, 1)}
            rows.append(row)
            print(f"{sample} seed {seed}: {reached} of {case.N_STARTS} reach the best chi2; "
                  f"others at delta chi2 {row['missed_delta_chi2']} ({row['time_s']} s)", flush=True)
    out = {"machine": machine_record(), "runs": rows,
           "criterion": f"delta chi2 < {case.REACHED_DELTA_CHI2} from the best of {case.N_STARTS} starts"}
    path = results_dir(quick) / "multistart.json"
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main("--quick" in sys.argv[1:])

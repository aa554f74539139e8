"""Regenerate every benchmark result.

    python -m benchmarks                  # all, into benchmarks/results/ (about an hour on 2 cores)
    python -m benchmarks --quick          # smallest size of each, into benchmarks/results/quick/
    python -m benchmarks fit_speed ...    # only the named ones

Each benchmark runs in its own process (float64 is a process-wide JAX switch).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
BENCHMARKS = {
    "reference_table": "accuracy against every shipped McStas and ray-tracer profile",
    "forward_speed": "forward-model evaluation and Jacobian time, float64 and float32",
    "speed_vs_error": "time against error: accuracy knob, exact reference at several ray counts, Paganin",
    "fit_speed": "the joint 10 BOA + 4 ICON fit; fit time against profiles, layers, pixels; memory",
    "fit_calibration": "coverage of the fit's 1-sigma errors over noise draws",
    "fit_starts": "fits from where users start: start kinds, cold and warm command times",
    "paganin_comparison": "the Paganin filter against the forward-model fit",
    "bench_radiograph": "TIFF stacks to profiles: time and peak memory",
    "bench_tof": "time-of-flight FITS and NeXus stacks to per-bin profiles: time and peak memory",
    "tof_scaling": "time-of-flight bins: plan, trace, compile and evaluation time against bin count",
    "image_rows": "fit-image: rows per second (750-pixel rows) and accuracy on a curved edge",
    "image_series": "fit-images: images per second, serial against a local Dask cluster",
    "sampler": "NUTS posterior sampling: effective samples per second, the oxide's SLD valley",
    "compile_cost": "the example's programs: graph size, compile and evaluation time, forward and Jacobian",
    "design_oxide": "fwdfit design's plan against the paper's distances on the oxide, tracer data",
    "cylinder_cost": "a rod's model against a block's: plan, compile, evaluation and Jacobian time",
}


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", metavar="NAME",
                        help="benchmarks to run (default: all): " + ", ".join(BENCHMARKS))
    parser.add_argument("--quick", action="store_true", help="smallest size of each (CI smoke run)")
    args = parser.parse_args()
    unknown = [n for n in args.names if n not in BENCHMARKS]
    if unknown:
        parser.error(f"unknown benchmark {unknown[0]!r} (choose from {', '.join(BENCHMARKS)})")
    failed = []
    for name in args.names or list(BENCHMARKS):
        print(f"== {name}: {BENCHMARKS[name]}", flush=True)
        start = time.perf_counter()
        command = [sys.executable, str(HERE / f"{name}.py")] + (["--quick"] if args.quick else [])
        if subprocess.run(command).returncode != 0:
            failed.append(name)
        print(f"== {name}: {time.perf_counter() - start:.0f} s", flush=True)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

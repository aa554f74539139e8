"""Benchmark: TIFF stacks of a full measurement to a profile, wall time and peak memory.

Writes 60 sample, 10 open-beam and 5 dark uint16 frames of 2048 x 2048 (single-page
files, as the camera saves them) to a temporary folder, then runs
``fwdfit.images.profile_from_stacks`` in a fresh Python process per combination
method and reads that process's peak resident memory (``ru_maxrss``). The frames are
written by a process of their own: Linux carries the parent's peak into ``ru_maxrss``
of a child it starts, so the parent stays small. Prints the results as JSON and writes
them to ``benchmarks/results/radiograph.json``.

    PYTHONPATH=src python3 benchmarks/bench_radiograph.py
"""

import argparse
import json
import math
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import tifffile
from _results import results_dir

ROOT = Path(__file__).resolve().parents[1]
N_SAMPLE, N_OPEN, N_DARK = 60, 10, 5
OPEN_COUNTS, DARK_COUNTS = 2000.0, 100.0
TILT_DEG = 0.5
SPOTS_PER_FRAME = 200


def smooth_step(x: np.ndarray) -> np.ndarray:
    """0 to 1 over about 4 pixels around x = 0."""
    return 0.5 * (1 + np.tanh(x / 2.0))


def transmission(size: int) -> np.ndarray:
    """``(size, size)`` sample T: a box with refraction peaks, edges tilted by TILT_DEG."""
    rows, cols = np.mgrid[0:size, 0:size].astype(np.float32)
    across = cols - (rows - size / 2) * math.tan(math.radians(TILT_DEG))
    box = smooth_step(across - 0.35 * size) - smooth_step(across - 0.65 * size)
    peaks = (np.exp(-0.5 * ((across - 0.35 * size + 4) / 3) ** 2)
             + np.exp(-0.5 * ((across - 0.65 * size - 4) / 3) ** 2))
    return 1.0 - 0.25 * box + 0.15 * peaks


def write_stacks(folder: Path, size: int) -> None:
    """Write the three stacks as folders ``sample``, ``open``, ``dark`` of uint16 TIFFs."""
    rng = np.random.default_rng(0)
    dark = DARK_COUNTS + 5 * rng.standard_normal((size, size), np.float32)
    beams = {"sample": OPEN_COUNTS * transmission(size), "open": np.full((size, size), OPEN_COUNTS),
             "dark": np.zeros((size, size))}
    counts = {"sample": N_SAMPLE, "open": N_OPEN, "dark": N_DARK}
    for name, beam in beams.items():
        (folder / name).mkdir()
        for i in range(counts[name]):
            frame = dark + rng.poisson(beam) + 2 * rng.standard_normal((size, size), np.float32)
            frame = np.clip(np.round(frame), 0, 65535).astype(np.uint16)
            spots = rng.integers(0, size, (2, SPOTS_PER_FRAME))
            frame[spots[0], spots[1]] = 65535
            tifffile.imwrite(folder / name / f"{name}_{i:03d}.tif", frame)


def peak_rss_mb() -> float:
    """This process's peak resident memory, MiB (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run_profile(folder: Path, combine: str, size: int) -> None:
    """Run one profile in this (fresh) process and print its timing and memory as JSON."""
    from fwdfit.images import profile_from_stacks

    import_rss_mb = peak_rss_mb()
    start = time.perf_counter()
    profile = profile_from_stacks(folder / "sample", folder / "open", folder / "dark",
                                  roi=(24, size - 24, 24, size - 24), pixel_um=2.4,
                                  combine=combine, rotate=True)
    print(json.dumps({"combine": combine, "rotate": True,
                      "wall_time_s": round(time.perf_counter() - start, 2),
                      "peak_rss_mb": round(peak_rss_mb(), 1),
                      "rss_after_imports_mb": round(import_rss_mb, 1),
                      "angle_deg": round(profile.angle_deg, 4),
                      "median_T_err": float(np.median(profile.T_err))}))


def run_self(*options: str) -> str:
    """Run this script in a fresh process with ``options``; return its standard output."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(ROOT / "src")] + os.environ.get("PYTHONPATH", "").split(os.pathsep)))
    return subprocess.run([sys.executable, __file__, *options], env=env, check=True,
                          capture_output=True, text=True).stdout


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=2048, help="frame side, pixels")
    parser.add_argument("--quick", action="store_true", help="256 x 256 frames (CI smoke run)")
    parser.add_argument("--write", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--profile", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--combine", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.quick:
        args.size = 256
    if args.write:
        write_stacks(args.write, args.size)
        return
    if args.profile:
        run_profile(args.profile, args.combine, args.size)
        return
    with tempfile.TemporaryDirectory() as folder:
        start = time.perf_counter()
        run_self("--size", str(args.size), "--write", folder)
        write_time_s = time.perf_counter() - start
        runs = [json.loads(run_self("--size", str(args.size), "--combine", combine,
                                    "--profile", folder))
                for combine in ("median", "mean")]
    result = {"benchmark": "profile_from_stacks", "frame_shape": [args.size, args.size],
              "dtype": "uint16", "frames": {"sample": N_SAMPLE, "open": N_OPEN, "dark": N_DARK},
              "stack_mb_on_disk": round((N_SAMPLE + N_OPEN + N_DARK) * args.size**2 * 2 / 2**20),
              "write_time_s": round(write_time_s, 1), "runs": runs,
              "machine": {"python": platform.python_version(), "cpu_count": os.cpu_count(),
                          "platform": platform.platform()}}
    text = json.dumps(result, indent=2)
    print(text)
    (results_dir(args.quick) / "radiograph.json").write_text(text + "\n")


if __name__ == "__main__":
    main()

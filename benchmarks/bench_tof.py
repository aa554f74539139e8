"""Benchmark: time-of-flight stacks to per-bin profiles (``fwdfit profile --tof``).

Writes sample and open-beam stacks of 512 x 512 uint16 images (an MCP/Timepix
detector), N_BINS bins each, as FITS folders with ``*_Spectra.txt`` and as NeXus
files, then runs the command in a fresh Python process per format (ROI 100 rows x
400 columns, ``--rebin 4``) and reads that process's wall time and peak resident
memory. Prints the results as JSON and writes ``benchmarks/results/tof_ingest.json``.

    PYTHONPATH=src python3 benchmarks/bench_tof.py [--quick]
"""

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _results import results_dir

ROOT = Path(__file__).resolve().parents[1]
SIZE = 512
ROI = "200,300,50,450"


def write_stacks(folder: Path, n_bins: int) -> None:
    """FITS folders ``sample``, ``open`` and NeXus files ``sample.nxs``, ``open.nxs``."""
    import h5py
    from astropy.io import fits

    rng = np.random.default_rng(0)
    times_s = 1e-3 + 1e-5 * np.arange(n_bins)
    T = np.ones((SIZE, SIZE))
    T[:, SIZE // 2:] = 0.7
    for name, mean in (("sample", 40 * T), ("open", np.full((SIZE, SIZE), 40.0))):
        (folder / name).mkdir()
        with h5py.File(folder / f"{name}.nxs", "w") as handle:
            handle.attrs["default"] = "entry"
            entry = handle.create_group("entry")
            entry.attrs.update({"NX_class": "NXentry", "default": "data"})
            data = entry.create_group("data")
            data.attrs.update({"NX_class": "NXdata", "signal": "counts",
                               "axes": ["time_of_flight", ".", "."]})
            counts = data.create_dataset("counts", (n_bins, SIZE, SIZE), np.uint16,
                                         chunks=(1, SIZE, SIZE))
            data.create_dataset("time_of_flight", data=times_s * 1e6).attrs["units"] = "us"
            for index in range(n_bins):
                image = rng.poisson(mean).astype(np.uint16)
                fits.PrimaryHDU(image).writeto(folder / name / f"{name}_{index:05d}.fits")
                counts[index] = image
        lines = [f"{t:.6E}\t0" for t in times_s]
        (folder / name / f"{name}_Spectra.txt").write_text("\r\n".join(lines) + "\r\n")


def run_one(folder: Path, kind: str) -> None:
    """Run the command in this (fresh) process; print wall time and peak memory as JSON."""
    from fwdfit.cli import main

    inputs = {"fits": ("sample", "open"), "nexus": ("sample.nxs", "open.nxs")}[kind]
    start = time.perf_counter()
    status = main(["profile", "--tof", "--sample", str(folder / inputs[0]), "--open",
                   str(folder / inputs[1]), "--roi", ROI, "--pixel-um", "55",
                   "--flight-path-m", "56.4", "--rebin", "4", "--out", str(folder / f"out_{kind}")])
    wall_s = time.perf_counter() - start
    print(json.dumps({"status": status, "wall_s": round(wall_s, 2),
                      "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="40 bins instead of 400")
    parser.add_argument("--run", nargs=2, metavar=("FOLDER", "KIND"), help=argparse.SUPPRESS)
    parser.add_argument("--write", nargs=2, metavar=("FOLDER", "N_BINS"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.run:
        run_one(Path(args.run[0]), args.run[1])
        return
    if args.write:  # in a process of its own: Linux carries a parent's peak memory
        write_stacks(Path(args.write[0]), int(args.write[1]))  # into its children
        return
    n_bins = 40 if args.quick else 400
    results = {"n_bins": n_bins, "image": f"{SIZE}x{SIZE} uint16", "roi": ROI, "rebin": 4}
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        subprocess.run([sys.executable, __file__, "--write", tmp, str(n_bins)], check=True)
        results["write_s"] = round(time.perf_counter() - start, 1)
        for kind in ("fits", "nexus"):
            run = subprocess.run([sys.executable, __file__, "--run", tmp, kind], check=True,
                                 capture_output=True, text=True,
                                 env={**os.environ, "PYTHONPATH": str(ROOT / "src")})
            results[kind] = json.loads(run.stdout.strip().splitlines()[-1])
    print(json.dumps(results, indent=2))
    (results_dir(args.quick) / "tof_ingest.json").write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()

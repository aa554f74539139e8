"""Image series (``fwdfit fit-images``): images per second fitted serially against a Dask
LocalCluster of two worker processes, and whether both give the same numbers.

The series is the exact Monte Carlo reference (``fwdfit.trace_reference_rows``), not the
model: a 400 µm Al block (2 mm deep, tilt 0.24°) at ICON (circular 40 mm at 5.5 m, 2.7 Å
line, 8.5 mm), images of ``--rows`` rows x 300 pixels of 2.4 µm, image i shifted by 4.8 (i mod 8) µm
and its rows by a 3 µm sinusoid, 0.3 % Gaussian noise. The compiled programs are made
once beforehand (a throwaway fit into the persistent cache), so both runs measure fitting
and loading the programs, as a user's second run does; the Dask figure includes starting
the cluster (reported apart as well).

    python benchmarks/image_series.py [--images N] [--rows R] [--quick]

Writes ``benchmarks/results/image_series.json`` (``--quick``: 4 images, into results/quick/).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
import tifffile  # noqa: E402

import fwdfit  # noqa: E402
from _results import machine_record, results_dir  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from helpers import gaussian_line_table  # noqa: E402
from test_image_series import N_COLS, NOISE, PIXEL_UM, SHIFT_UM, X0_UM, series_scene  # noqa: E402

AL = fwdfit.constants_from_formula("Al", 2.70)


def make_series(folder: Path, n_images: int, n_rows: int) -> list[Path]:
    lam, weight = gaussian_line_table(2.7, 0.15)
    rows = np.arange(n_rows)
    wanted = (SHIFT_UM * (np.arange(n_images) % 8)[:, None] + 3.0 * np.sin(2 * np.pi * rows / n_rows)[None]).ravel()
    reference = fwdfit.trace_reference_rows(
        [fwdfit.ReferenceLayer(400.0, AL.sld_e6_per_A2, AL.mu_per_m, AL.mu_per_m_per_A)],
        centres_um=wanted, x0_um=X0_UM, pixel_um=PIXEL_UM, n_pixels=N_COLS, sub=8, spectrum_lambda_A=lam,
        spectrum_weight=weight, n_rays=2_000_000, seed=3, depth_mm=2.0, tilt_deg=0.24, aperture="circular",
        aperture_mm=40.0, aperture_distance_m=5.5, distance_mm=8.5)
    images = reference.T.reshape(n_images, n_rows, N_COLS)
    images = images + NOISE * np.random.default_rng(1).standard_normal(images.shape)
    paths = []
    for i, image in enumerate(images):
        paths.append(folder / f"proj_{i:03d}.tif")
        tifffile.imwrite(paths[-1], image.astype(np.float32))
    fwdfit.save_scene(series_scene(folder), folder / "scene.toml")
    return paths


def _timed_run(scene: Path, images, out: Path, workers: int) -> float:
    from fwdfit.images import fit_series

    begin = time.perf_counter()
    lines = fit_series(scene, images, out, workers=workers)
    assert all(line["status"] == "ok" for line in lines), lines
    return time.perf_counter() - begin


def _largest_difference(a: Path, b: Path, images) -> float:
    """Largest relative difference of any rows.csv number between two runs' outputs."""
    worst = 0.0
    for image in images:
        x = np.genfromtxt(a / image.stem / "rows.csv", delimiter=",", skip_header=1)
        y = np.genfromtxt(b / image.stem / "rows.csv", delimiter=",", skip_header=1)
        both = np.isfinite(x)
        assert np.array_equal(both, np.isfinite(y))
        worst = max(worst, float(np.max(np.abs(x[both] - y[both]) / np.maximum(np.abs(x[both]), 1e-300))))
    return worst


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=8)
    parser.add_argument("--rows", type=int, default=12)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    n_images = 4 if args.quick else args.images
    from distributed import Client, LocalCluster

    with tempfile.TemporaryDirectory(prefix="fwdfit-series-") as tmp:
        tmp = Path(tmp)
        os.environ.setdefault("FWDFIT_CACHE_DIR", str(tmp / "cache"))
        images = make_series(tmp, n_images, args.rows)
        scene = tmp / "scene.toml"
        begin = time.perf_counter()
        _timed_run(scene, images[:1], tmp / "warm", workers=1)  # compiles into the persistent cache
        warm_s = time.perf_counter() - begin
        serial_s = _timed_run(scene, images, tmp / "serial", workers=1)
        begin = time.perf_counter()
        with LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None) as cluster, Client(cluster):
            startup_s = time.perf_counter() - begin
        dask_s = _timed_run(scene, images, tmp / "dask", workers=2)
        difference = _largest_difference(tmp / "serial", tmp / "dask", images)
    record = {
        "images": n_images, "rows": args.rows, "pixels": N_COLS,
        "first_image_with_compilation_s": warm_s,
        "serial_s": serial_s, "serial_images_per_s": n_images / serial_s,
        "serial_rows_per_s": n_images * args.rows / serial_s,
        "dask_2_workers_s": dask_s, "dask_2_workers_images_per_s": n_images / dask_s,
        "dask_cluster_startup_s": startup_s,
        "dask_vs_serial_largest_relative_difference": difference,
        "load_average_1min": os.getloadavg()[0], "machine": machine_record(),
    }
    path = results_dir(args.quick) / "image_series.json"
    path.write_text(json.dumps(record, indent=2) + "\n")
    print(json.dumps(record, indent=2))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

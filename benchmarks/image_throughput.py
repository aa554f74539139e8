"""Whole-image throughput of ``fwdfit fit-image``: rows per second of everything after
compilation (faces in every row, two shared fits, two rounds of per-row fits) and the
process's peak memory, on 750-pixel rows and on a 2048 x 2048 radiograph.

Images: the exact Monte Carlo reference (``fwdfit.trace_reference_rows``, one trace) of the
Al block of ``image_rows.py`` (1000 µm x 2 mm, tilt 0.24°, ICON 2.7 Å line at 8.5 mm, 2.4 µm
pixels), its centre following a 20 µm peak-to-peak sinusoid plus a parabola over the rows,
Poisson noise of 10^4 open-beam counts per pixel; no error image. Each fit runs as a user
runs it, ``fwdfit.cli`` in a fresh process: the 750-pixel image twice (an empty compilation
cache, then the cache that run filled), the 2048 x 2048 one once (cold). Peak memory is the
fit process's maximum resident set (``VmHWM`` of /proc/self/status: getrusage's maximum
would keep the parent's, which held the traced image, across exec), beside that of the
same process after importing fwdfit and JAX (``baseline``).

    python benchmarks/image_throughput.py [--rows N] [--big N] [--quick]

Writes ``benchmarks/results/image_throughput.json`` (``--quick``: 100 rows, a 512 x 512
image instead, into results/quick/). Run it on an otherwise idle machine: the load average
before and after is recorded.
"""

from __future__ import annotations

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

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))

PIXEL_UM = 2.4
COUNTS = 1e4


def radiograph(n_rows: int, n_cols: int, x0_um: float, seed: int = 0, n_rays: int = 12_000_000):
    """(centres (rows,), noisy T (rows, n_cols)) of the exact reference (see the module's docstring)."""
    import fwdfit
    from helpers import gaussian_line_table

    al = fwdfit.constants_from_formula("Al", 2.70)
    lam, weight = gaussian_line_table(2.7, 0.15)
    rows = np.arange(n_rows)
    wanted = 3.0 + 10.0 * np.sin(2 * np.pi * rows / n_rows) + 8.0 * (rows / n_rows - 0.5) ** 2
    reference = fwdfit.trace_reference_rows(
        [fwdfit.ReferenceLayer(1000.0, al.sld_e6_per_A2, al.mu_per_m, al.mu_per_m_per_A)],
        centres_um=wanted, x0_um=x0_um, pixel_um=PIXEL_UM, n_pixels=n_cols, depth_mm=2.0, tilt_deg=0.24,
        aperture="circular", aperture_mm=40.0, aperture_distance_m=5.5, distance_mm=8.5,
        spectrum_lambda_A=lam, spectrum_weight=weight, n_rays=n_rays, seed=seed)
    noisy = np.random.default_rng(seed + 1).poisson(COUNTS * reference.T) / COUNTS
    return reference.centres_um, noisy


def write_case(folder: Path, n_rows: int, n_cols: int) -> tuple[Path, np.ndarray]:
    """The image (T.tif) and its scene (scene.toml, start 1100 µm) in ``folder``; the true centres."""
    import fwdfit
    import tifffile
    from helpers import image_scene

    x0 = -0.5 * n_cols * PIXEL_UM
    centres, image = radiograph(n_rows, n_cols, x0)
    folder.mkdir(parents=True, exist_ok=True)
    tifffile.imwrite(folder / "T.tif", image.astype(np.float32))
    scene = image_scene(folder / "T.tif", thickness_um=1100.0, x0_um=x0, n_cols=n_cols, pixel_um=PIXEL_UM)
    return fwdfit.save_scene(scene, folder / "scene.toml"), centres


def _peak_rss_mb() -> float:
    """This process's peak resident set (MiB): VmHWM where /proc has it, else getrusage's."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def child(scene: str, out: str) -> None:
    """One fit-image in this (fresh) process; prints a JSON line of timings and memory."""
    begin = time.perf_counter()
    import jax

    jax.config.update("jax_enable_x64", True)
    from fwdfit.cli import main

    baseline = _peak_rss_mb()
    imported = time.perf_counter()
    status = main(["fit-image", scene, "--out", out, "--quiet"])
    end = time.perf_counter()
    print(json.dumps({"status": status, "import_s": imported - begin, "command_s": end - imported,
                      "peak_rss_mb": _peak_rss_mb(), "baseline_rss_mb": baseline}))


def run(scene: Path, out: Path, cache: Path, centres: np.ndarray) -> dict:
    """fit-image SCENE in a fresh process with the compilation cache ``cache``: its record."""
    env = {**os.environ, "FWDFIT_CACHE_DIR": str(cache)}
    begin = time.perf_counter()
    done = subprocess.run([sys.executable, __file__, "--child", str(scene), str(out)], env=env,
                          capture_output=True, text=True)
    wall = time.perf_counter() - begin
    if done.returncode != 0 or not done.stdout.strip():
        raise SystemExit(f"fit-image failed: {done.stderr.strip()[-2000:]}")
    process = json.loads(done.stdout.strip().splitlines()[-1])
    result = json.loads((out / "result.json").read_text())
    from helpers import read_table

    rows = read_table(out / "rows.csv")
    good = rows["flag"] == 0
    n_rows = len(rows["flag"])
    fit_s = result["solve_time_s"]
    return {
        "rows": n_rows, "exit_status": process["status"],
        "process_wall_s": round(wall, 2), "import_s": round(process["import_s"], 2),
        "compile_s": round(result["compile_time_s"], 2),
        "fit_s": round(fit_s, 2),  # after compilation: faces, shared fits, per-row fits
        "whole_image_rows_per_s": round(n_rows / fit_s, 1),
        "with_compile_rows_per_s": round(n_rows / (fit_s + result["compile_time_s"]), 1),
        "per_row_fits_rows_per_s": round(result["rows_per_s"], 1),
        "peak_rss_mb": round(process["peak_rss_mb"]), "baseline_rss_mb": round(process["baseline_rss_mb"]),
        "rows_good": int(good.sum()),
        "centre_within_1um": float(np.mean(np.abs(rows["centre_um"][good] - centres[good]) < 1.0)),
        "thickness_um": result["parameters"]["layers.Al.thickness_um"]["value"],
        "chi2_reduced": result["chi2_reduced"], "shared_chi2_reduced": result["shared_fit"]["chi2_reduced"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=200, help="rows of the 750-pixel image")
    parser.add_argument("--big", type=int, default=2048, help="side of the square image (0: none)")
    parser.add_argument("--quick", action="store_true", help="100 rows and a 512 x 512 image")
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(*args.child)
        return
    from _results import machine_record, write_result

    rows, big = (100, 512) if args.quick else (args.rows, args.big)
    load = [os.getloadavg()[0]]
    record: dict = {"pixel_um": PIXEL_UM, "open_beam_counts": COUNTS}
    with tempfile.TemporaryDirectory() as temporary:
        folder = Path(temporary)
        scene, centres = write_case(folder / "rows750", rows, 750)
        cache = folder / "cache"
        record["rows_750"] = {"cold": run(scene, folder / "out_cold", cache, centres),
                              "warm": run(scene, folder / "out_warm", cache, centres)}
        load.append(os.getloadavg()[0])
        if big:
            scene, centres = write_case(folder / "big", big, big)
            record[f"image_{big}x{big}"] = run(scene, folder / "out_big", folder / "cache_big", centres)
            load.append(os.getloadavg()[0])
    record["load_average_1min"] = load  # before, after the 750-pixel runs, after the big one
    record["machine"] = machine_record()
    print(json.dumps(record, indent=2))
    write_result("image_throughput", record, args.quick)


if __name__ == "__main__":
    main()

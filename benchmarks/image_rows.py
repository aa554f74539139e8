"""Image fits: rows per second, and accuracy on a radiograph whose edge curves across rows.

The radiograph is the exact Monte Carlo reference (``fwdfit.trace_reference_rows``: one
trace, each row summed with the stack moved to its own centre), not the model: the Al
block (1000 µm x 2 mm, tilt 0.24°) at ICON (circular 40 mm at 5.5 m, 2.7 Å line,
8.5 mm), 750 pixels of 2.4 µm per row, the centre following a 20 µm peak-to-peak
sinusoid plus a parabola over the rows, Poisson noise of 10^4 open-beam counts per pixel
(1 % in the open beam). No error image: the fit estimates the noise.

Reported: compile time, the whole fit (after compilation) and the rate of the per-row
fits (last round, rows per second), against one row fitted alone as a profile
(``fwdfit.Fitter`` on that row, all five parameters, compiled beforehand); and the
accuracy the issue asks for (centres within 1 µm of the truth, RMS of T_att against the
reference's, thickness and SLD).

    python benchmarks/image_rows.py [--rows N] [--quick]

Writes ``benchmarks/results/image_rows.json`` (``--quick``: 40 rows, into results/quick/).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
import tifffile  # noqa: E402

import fwdfit  # noqa: E402
from _results import machine_record, write_result  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from helpers import gaussian_line_table, image_scene  # noqa: E402

AL = fwdfit.constants_from_formula("Al", 2.70)
N_COLS, PIXEL_UM, X0_UM = 750, 2.4, -900.0
COUNTS = 1e4  # open-beam counts per pixel


def scene(folder: Path) -> fwdfit.Scene:
    """The Al block (start 1100 µm) of ``helpers.image_scene``, the image T.tif in ``folder``."""
    return image_scene(folder / "T.tif", thickness_um=1100.0, x0_um=X0_UM, n_cols=N_COLS, pixel_um=PIXEL_UM)


def radiograph(n_rows: int, seed: int = 0):
    """(centres (rows,), T_noisy, T_att (rows, N_COLS)) of the exact reference."""
    lam, weight = gaussian_line_table(2.7, 0.15)
    rows = np.arange(n_rows)
    wanted = 3.0 + 10.0 * np.sin(2 * np.pi * rows / n_rows) + 8.0 * (rows / n_rows - 0.5) ** 2
    reference = fwdfit.trace_reference_rows(
        [fwdfit.ReferenceLayer(1000.0, AL.sld_e6_per_A2, AL.mu_per_m, AL.mu_per_m_per_A)],
        centres_um=wanted, x0_um=X0_UM, pixel_um=PIXEL_UM, n_pixels=N_COLS, depth_mm=2.0, tilt_deg=0.24,
        aperture="circular", aperture_mm=40.0, aperture_distance_m=5.5, distance_mm=8.5,
        spectrum_lambda_A=lam, spectrum_weight=weight, n_rays=12_000_000, seed=seed)
    rng = np.random.default_rng(seed + 1)
    noisy = rng.poisson(COUNTS * reference.T) / COUNTS
    return reference.centres_um, noisy, reference.T_att


def one_row_alone(folder: Path, row: np.ndarray) -> dict:
    """One row fitted as a profile (all five parameters): compile and solve times."""
    x_um = X0_UM + (np.arange(N_COLS) + 0.5) * PIXEL_UM
    lines = ["x_um,T"] + [f"{x:.6f},{t:.9g}" for x, t in zip(x_um, row)]
    (folder / "row.csv").write_text("\n".join(lines) + "\n")
    one = scene(folder)
    row_profile = dataclasses.replace(one.profiles[0], image_file=None, file=folder / "row.csv")
    fwdfit.save_scene(dataclasses.replace(one, profiles=(row_profile,)), folder / "row.toml")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fitter = fwdfit.Fitter(fwdfit.load_scene(folder / "row.toml"))
        times = []
        for _ in range(2):
            begin = time.perf_counter()
            result = fitter()
            times.append(time.perf_counter() - begin)
    return {"compile_time_s": fitter.compile_time_s, "solve_time_s": min(times),
            "rows_per_s": 1.0 / min(times), "model_evaluations": result.n_evaluations}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=200)
    parser.add_argument("--quick", action="store_true", help="40 rows")
    args = parser.parse_args()
    n_rows = 40 if args.quick else args.rows
    load_before = os.getloadavg()[0]
    begin = time.perf_counter()
    centres, image, T_att_true = radiograph(n_rows)
    trace_s = time.perf_counter() - begin
    with tempfile.TemporaryDirectory() as temporary:
        folder = Path(temporary)
        tifffile.imwrite(folder / "T.tif", image.astype(np.float32))
        fwdfit.save_scene(scene(folder), folder / "scene.toml")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fwdfit.enable_compilation_cache(folder / "cache")  # cold: compiles
            result = fwdfit.fit_image(folder / "scene.toml", progress=True)
        alone = one_row_alone(folder, image[n_rows // 2])
    good = result.good
    miss = np.abs(result.centre_um - centres)
    record = {
        "rows": n_rows, "pixels_per_row": N_COLS, "trace_time_s": trace_s,
        "compile_time_s": result.compile_time_s, "fit_time_s": result.wall_time_s,
        "rows_per_s": result.rows_per_s,
        "image_rows_per_s_overall": n_rows / result.wall_time_s,
        "one_row_alone": alone,
        "accuracy": {
            "rows_good": int(good.sum()),
            "centre_within_1um": float(np.mean(miss[good] < 1.0)),
            "centre_error_rms_um": float(np.sqrt(np.mean(miss[good] ** 2))),
            "T_att_rms": float(np.sqrt(np.mean((result.T_att[good] - T_att_true[good]) ** 2))),
            "thickness_um": result.shared["layers.Al.thickness_um"][0],
            "sld_e6_per_A2": result.shared["layers.Al.sld_e6_per_A2"][0],
            "sld_true": AL.sld_e6_per_A2,
            "chi2_reduced": result.chi2_reduced,
        },
        "load_average_1min": [load_before, os.getloadavg()[0]],  # other jobs slow every figure down
        "machine": machine_record(),
    }
    print(json.dumps(record, indent=2))
    write_result("image_rows", record, args.quick)


if __name__ == "__main__":
    main()

"""The forward model against every shipped reference case: a table of agreement.

Runs the model with default settings (accuracy 1e-3, float64) on every scene of
``tests/data/mcstas`` and ``tests/data/raytrace`` and compares each profile with its
reference, with the definitions the tests use (``tests/helpers.py``):

- RMS of T - T_ref and of T_att - T_att_ref over the whole profile;
- gain-peak height and loss-dip depth at each edge (``edge_heights``: extrema after a
  running mean over an eighth of the penumbra, loss from the reference's T_att), model,
  reference and relative difference;
- the reference's own noise: RMS of its T_err over the profile, and its T_err at the
  bin of each extremum.

Writes ``benchmarks/results/reference_table.json`` and ``reference_table.md``.

    PYTHONPATH=src python3 benchmarks/reference_table.py
"""

from __future__ import annotations

import json
import platform
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # one definition of the metrics, shared with the tests

import fwdfit  # noqa: E402
from helpers import (  # noqa: E402
    MCSTAS, RAYTRACE, edge_heights, load_reference, rms, running_mean, smoothing_pixels)

RESULTS = ROOT / "benchmarks" / "results"
SCENES = {
    "mcstas_boa_tilt0.00": MCSTAS / "scene_boa_tilt0.00.toml",
    "mcstas_boa_tilt0.24": MCSTAS / "scene_boa_tilt0.24.toml",
    "mcstas_icon_tilt0.00": MCSTAS / "scene_icon_tilt0.00.toml",
    "mcstas_icon_tilt0.24": MCSTAS / "scene_icon_tilt0.24.toml",
    "raytrace_al_boa_tilt0": RAYTRACE / "al_boa_tilt0" / "scene.toml",
    "raytrace_al_boa_tilt0.24_psf": RAYTRACE / "al_boa_tilt0.24_psf" / "scene.toml",
    "raytrace_al_icon_tilt0.24": RAYTRACE / "al_icon_tilt0.24" / "scene.toml",
    "raytrace_oxide5_boa": RAYTRACE / "oxide5_boa" / "scene.toml",
}


def _extremum_errors(ref, n, centre):
    """The reference's 1-sigma error of (gain, loss) at each side's extremum bin, smoothed
    like the heights (a running mean of n bins divides independent errors by sqrt(n))."""
    x, T = ref["x_um"], running_mean(ref["T"], n)
    out = []
    for side in (x < centre, x > centre):
        i_max, i_min = np.argmax(T[side]), np.argmin(T[side])
        err, err_att = ref["T_err"][side], ref["T_att_err"][side]
        out.append((float(err[i_max] / np.sqrt(n)),
                    float(np.hypot(err[i_min], err_att[i_min]) / np.sqrt(n))))
    return out


def compare_case(case: str, path: Path) -> tuple[list[dict], float]:
    """One row per profile of one scene, and the wall time of build + compile + run."""
    start = time.perf_counter()
    scene = fwdfit.load_scene(path)
    T_all, T_att_all = eqx.filter_jit(fwdfit.build_model(scene))(fwdfit.initial_params(scene))
    T_all = [np.asarray(t) for t in T_all]
    T_att_all = [np.asarray(t) for t in T_att_all]
    seconds = time.perf_counter() - start
    rows = []
    for profile, T, T_att in zip(scene.profiles, T_all, T_att_all):
        ref = load_reference(path.parent, profile.name)
        if not np.allclose(profile.x_um, ref["x_um"], rtol=0, atol=1e-6):
            raise RuntimeError(f"{case}/{profile.name}: scene grid differs from the reference's")
        instrument = scene.instruments[profile.instrument]
        n = smoothing_pixels(profile.distance_mm, instrument.aperture_mm,
                             instrument.aperture_distance_m, instrument.pixel_um)
        centre = scene.sample.centre_um
        mine = edge_heights(ref["x_um"], T, ref["T_att"], centre, n)
        theirs = edge_heights(ref["x_um"], ref["T"], ref["T_att"], centre, n)
        raw_mine = edge_heights(ref["x_um"], T, ref["T_att"], centre, 1)
        raw_theirs = edge_heights(ref["x_um"], ref["T"], ref["T_att"], centre, 1)
        errors = _extremum_errors(ref, n, centre)
        edges = {}
        for s, side in enumerate(("left", "right")):
            for k, kind in enumerate(("gain", "loss")):
                edges[f"{side}_{kind}"] = {
                    "model": mine[s][k], "reference": theirs[s][k],
                    "rel_diff": mine[s][k] / theirs[s][k] - 1.0,
                    "reference_err": errors[s][k],
                    "raw_model": raw_mine[s][k], "raw_reference": raw_theirs[s][k],
                }
        rows.append({
            "case": case, "profile": profile.name, "distance_mm": profile.distance_mm,
            "smoothing_pixels": n,
            "rms_T": rms(T - ref["T"]), "rms_T_att": rms(T_att - ref["T_att"]),
            "max_abs_T": float(np.max(np.abs(T - ref["T"]))),
            "ref_noise_rms_T_err": rms(ref["T_err"]), "ref_noise_rms_T_att_err": rms(ref["T_att_err"]),
            "edges": edges,
        })
    return rows, seconds


def markdown(rows: list[dict], timings: dict[str, float]) -> str:
    lines = [
        "# Forward model vs shipped references (default settings, float64)",
        "",
        "Generated by `PYTHONPATH=src python3 benchmarks/reference_table.py`. RMS over the whole",
        "profile; gain = max(T) - 1 and loss = T_att_ref - T at the dip, per edge (L/R), after a",
        "running mean of `n` pixels (an eighth of the penumbra) applied to model and reference",
        "alike; Δ = model / reference - 1. Noise: the reference's RMS T_err over the profile and",
        "its (smoothed) error at the extremum bins, largest of the four. Tolerances in the tests:",
        "RMS 0.002, |Δ| 5 %.",
        "",
        "| case | profile | n | RMS T | RMS T_att | ref noise | gain L model/ref (Δ) | loss L model/ref (Δ) "
        "| gain R model/ref (Δ) | loss R model/ref (Δ) | peak err (ref) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        cells = []
        for key in ("left_gain", "left_loss", "right_gain", "right_loss"):
            e = r["edges"][key]
            cells.append(f"{e['model']:.4f}/{e['reference']:.4f} ({100 * e['rel_diff']:+.1f} %)")
        peak_err = max(e["reference_err"] for e in r["edges"].values())
        lines.append(f"| {r['case']} | {r['profile']} | {r['smoothing_pixels']} | {r['rms_T']:.5f} "
                     f"| {r['rms_T_att']:.5f} | {r['ref_noise_rms_T_err']:.5f} | " + " | ".join(cells)
                     + f" | {peak_err:.4f} |")
    worst = max(rows, key=lambda r: max(abs(e["rel_diff"]) for e in r["edges"].values()))
    worst_rel = max(abs(e["rel_diff"]) for e in worst["edges"].values())
    lines += [
        "",
        f"Worst RMS T: {max(r['rms_T'] for r in rows):.5f}; worst RMS T_att: "
        f"{max(r['rms_T_att'] for r in rows):.5f}; worst peak difference: {100 * worst_rel:.1f} % "
        f"({worst['case']}/{worst['profile']}); {len(rows)} profiles.",
        "",
        "Wall time per scene (load, build, compile, run): "
        + ", ".join(f"{k} {v:.2f} s" for k, v in timings.items())
        + " (scenes whose compiled shapes match an earlier one reuse its compilation).",
        "",
    ]
    return "\n".join(lines)


def main() -> None:
    rows, timings = [], {}
    for case, path in SCENES.items():
        case_rows, seconds = compare_case(case, path)
        rows += case_rows
        timings[case] = seconds
        print(f"{case}: {len(case_rows)} profiles, {seconds:.1f} s", flush=True)
    RESULTS.mkdir(parents=True, exist_ok=True)
    meta = {"jax": jax.__version__, "device": str(jax.devices()[0]), "python": platform.python_version(),
            "machine": platform.machine(), "accuracy": "default (scene's, 1e-3)", "dtype": "float64"}
    (RESULTS / "reference_table.json").write_text(json.dumps(
        {"meta": meta, "timings_s": timings, "profiles": rows}, indent=1) + "\n")
    (RESULTS / "reference_table.md").write_text(markdown(rows, timings))
    print((RESULTS / "reference_table.md").read_text())


if __name__ == "__main__":
    main()

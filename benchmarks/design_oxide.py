"""Does ``fwdfit design``'s plan beat the paper's evenly spaced distances? The five-layer oxide.

The oxide scene (tests/data/raytrace/oxide5_boa: Al 1000 µm with two oxide layers each
side, BOA white beam) with seven free parameters (tilt, centre, the three thicknesses, the
two oxides' SLDs); target: the inner oxide's thickness. Candidates: the paper's ten
distances 1.1, 4.8, ..., 34.4 mm; total exposure 10 units; 0.5 % noise per open-beam
pixel in one unit. The "paper" plan is one unit at each distance (``fwdfit design``'s
"even" plan over these candidates).

Each plan is then measured: the independent ray tracer's profile at each distance it uses
(``--rays`` rays), plus Gaussian noise of 0.005 sqrt(T / t) for its exposure t, 20 draws;
every draw fitted by ``fwdfit.Fitter`` from the truth. Reported: the predicted and the
observed (RMS over draws, about the truth) error of the target, per plan.

    python benchmarks/design_oxide.py [--draws N] [--rays R]

Writes benchmarks/results/design_oxide.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import fwdfit  # noqa: E402
from _results import machine_record, results_dir  # noqa: E402

SCENE = Path(__file__).resolve().parents[1] / "tests" / "data" / "raytrace" / "oxide5_boa" / "scene.toml"
TARGET = "layers.oxide1_left.thickness_um"
VARY = ("sample.tilt_deg", "sample.centre_um", "layers.oxide2_left.thickness_um", TARGET,
        "layers.Al.thickness_um", "layers.oxide2_left.sld_e6_per_A2", "layers.oxide1_left.sld_e6_per_A2")
PAPER_DISTANCES_MM = tuple(round(1.1 + 3.7 * k, 1) for k in range(10))
NOISE = 0.005
EXPOSURE = 10.0


def _traced(scene: fwdfit.Scene, distance_mm: float, n_rays: int) -> np.ndarray:
    """The tracer's T on the pixels of the scene's widest profile, at ``distance_mm``."""
    instrument = scene.instruments[""]
    spectrum = scene.spectra["white"]
    x = max((p.x_um for p in scene.profiles), key=len)
    edges = np.concatenate([x - instrument.pixel_um / 2, x[-1:] + instrument.pixel_um / 2])
    layers = []
    for layer in scene.sample.layers:
        root = next(l for l in scene.sample.layers if l.name == (layer.same_as or layer.name))
        layers.append(fwdfit.ReferenceLayer(root.thickness_um, root.sld_e6_per_A2, root.mu_per_m))
    result = fwdfit.trace_reference(
        layers, depth_mm=scene.sample.depth_mm, tilt_deg=scene.sample.tilt_deg, centre_um=scene.sample.centre_um,
        aperture=instrument.aperture, aperture_mm=instrument.aperture_mm,
        aperture_distance_m=instrument.aperture_distance_m, distance_mm=distance_mm,
        spectrum_lambda_A=spectrum.lambda_A, spectrum_weight=spectrum.weight, pixel_edges_um=edges,
        n_rays=n_rays, seed=int(distance_mm * 10))
    return x, result.T


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=20)
    parser.add_argument("--rays", type=int, default=20_000_000)
    args = parser.parse_args()
    base = fwdfit.load_scene(SCENE)
    scene = dataclasses.replace(base, fit=fwdfit.FitSpec(VARY))
    start = time.perf_counter()
    plan = fwdfit.design(scene, target=[TARGET], distances_mm=PAPER_DISTANCES_MM, spectra=["white"],
                         exposure=EXPOSURE, noise=NOISE)
    design_s = time.perf_counter() - start
    plans = {"design": plan.plans["optimal"], "paper": plan.plans["even"]}
    truth = float(plan.values[plan.targets[0]])
    traced = {}
    record = {"target": TARGET, "truth": truth, "noise": NOISE, "exposure": EXPOSURE, "draws": args.draws,
              "rays": args.rays, "design_s": round(design_s, 1), "plans": {}}
    rng = np.random.default_rng(0)
    for name, exposures in plans.items():
        used = [(c, t) for c, t in zip(plan.candidates, exposures) if t > 0]
        for c, _ in used:
            if c.distance_mm not in traced:
                traced[c.distance_mm] = _traced(scene, c.distance_mm, args.rays)
        profiles = tuple(fwdfit.Profile(f"d{c.distance_mm:g}", c.distance_mm, "white", "", traced[c.distance_mm][0])
                         for c, _ in used)
        T = [traced[c.distance_mm][1] for c, _ in used]
        sigma = [NOISE * np.sqrt(np.clip(t_true, 1e-6, None) / t) for t_true, (_, t) in zip(T, used)]
        fitter = fwdfit.Fitter(dataclasses.replace(scene, profiles=tuple(
            dataclasses.replace(p, T=t, T_err=s) for p, t, s in zip(profiles, T, sigma))))
        estimates, chi2 = [], []
        for _ in range(args.draws):
            data = [t + s * rng.standard_normal(t.shape) for t, s in zip(T, sigma)]
            result = fitter(data, sigma, start=plan.values)
            estimates.append(result[TARGET][0])
            chi2.append(result.chi2_reduced)
        estimates = np.array(estimates)
        record["plans"][name] = {
            "measurements": {f"{c.distance_mm:g} mm": round(float(t), 3) for c, t in used},
            "predicted_err_um": float(plan.errors(exposures)[plan.targets[0]]),
            "observed_rms_err_um": float(np.sqrt(np.mean((estimates - truth) ** 2))),
            "observed_std_um": float(np.std(estimates, ddof=1)),
            "mean_bias_um": float(np.mean(estimates) - truth),
            "chi2_reduced_median": float(np.median(chi2))}
        print(name, record["plans"][name], flush=True)
    record["machine"] = machine_record()
    out = results_dir(False) / "design_oxide.json"
    out.write_text(json.dumps(record, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

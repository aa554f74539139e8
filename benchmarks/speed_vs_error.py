"""Speed against error: the model's accuracy knob, the exact reference, the Paganin filter.

    python benchmarks/speed_vs_error.py [--quick]

For the BOA white-beam distances (tests/data/raytrace/al_boa_tilt0) and the ICON
lines (tests/data/raytrace/al_icon_tilt0.24):

- the model at a sweep of ``accuracy`` settings: time per evaluation (all profiles
  of the case, after compilation) against the RMS error in T relative to the
  converged model (accuracy 1e-5), and against the shared ray-tracer data;
- fwdfit's exact Monte Carlo reference at several ray counts (error ~ 1/sqrt(rays));
- the Paganin filter (b_factor 1): time and RMS of T_filtered - T_att.

Writes benchmarks/results/speed_vs_error.{json,png}; ``--quick`` runs a smaller sweep
into benchmarks/results/quick/.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import numpy as np  # noqa: E402

import fwdfit  # noqa: E402
from _results import results_dir  # noqa: E402
from fwdfit.model import DEPTH_PIECES  # noqa: E402
from fwdfit.paganin import profile_tau_um2  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CASES = {"BOA white beam": ROOT / "tests/data/raytrace/al_boa_tilt0/scene.toml",
         "ICON lines": ROOT / "tests/data/raytrace/al_icon_tilt0.24/scene.toml"}
DEFAULT = 1e-3


def _timed(fn, repeats: int) -> float:
    jax.block_until_ready(fn())
    start = time.perf_counter()
    for _ in range(repeats):
        jax.block_until_ready(fn())
    return (time.perf_counter() - start) / repeats


def _rms(a: list, b: list) -> float:
    return float(np.sqrt(np.mean(np.concatenate([(np.asarray(x) - np.asarray(y)) ** 2 for x, y in zip(a, b)]))))


def model_sweep(scene, accuracies, converged, shared, repeats):
    rows = []
    params = fwdfit.initial_params(scene)
    for accuracy in accuracies:
        model = fwdfit.build_model(scene, accuracy)
        run = eqx.filter_jit(lambda m, p: m(p)).lower(model, params).compile()
        seconds = _timed(lambda: run(model, params), repeats)
        T = run(model, params)[0]
        rows.append({"accuracy": accuracy, "time_ms": 1e3 * seconds, "rms_vs_converged": _rms(T, converged),
                     "rms_vs_shared_reference": _rms(T, shared),
                     "wavelength_nodes": int(model.groups[0].wavelength_A.shape[1]),
                     "depth_nodes": [DEPTH_PIECES * len(g.z_nodes) for g in model.groups]})
        print(f"  accuracy {accuracy:.0e}: {rows[-1]['time_ms']:.1f} ms, rms {rows[-1]['rms_vs_converged']:.2e}",
              flush=True)
    return rows


def reference_sweep(scene, ray_counts, converged):
    rows = []
    layers = [fwdfit.ReferenceLayer(l.thickness_um, l.sld_e6_per_A2, l.mu_per_m, l.mu_per_m_per_A)
              for l in scene.sample.layers]
    for rays in ray_counts:
        start, T = time.perf_counter(), []
        for p in scene.profiles:
            instrument, spectrum = scene.instruments[p.instrument], scene.spectra[p.spectrum]
            lam = np.linspace(*spectrum.support_A, 2000)
            edges = np.append(p.x_um - 0.5 * instrument.pixel_um, p.x_um[-1] + 0.5 * instrument.pixel_um)
            T.append(fwdfit.trace_reference(
                layers, depth_mm=scene.sample.depth_mm, tilt_deg=scene.sample.tilt_deg,
                centre_um=scene.sample.centre_um, aperture=instrument.aperture,
                aperture_mm=instrument.aperture_mm, aperture_distance_m=instrument.aperture_distance_m,
                distance_mm=p.distance_mm, spectrum_lambda_A=lam, spectrum_weight=spectrum.density(lam),
                pixel_edges_um=edges, n_rays=rays, seed=1).T)
        rows.append({"rays_per_profile": rays, "time_ms": 1e3 * (time.perf_counter() - start),
                     "rms_vs_converged": _rms(T, converged)})
        print(f"  reference {rays:.0e} rays: {rows[-1]['time_ms']:.0f} ms, rms {rows[-1]['rms_vs_converged']:.2e}",
              flush=True)
    return rows


def paganin_row(scene, converged_att, repeats):
    layer = max(scene.sample.layers, key=lambda l: l.thickness_um)
    sims = fwdfit.simulate(scene, 1e-5)
    taus = [profile_tau_um2(scene, p, layer) for p in scene.profiles]
    pixel = scene.instruments[""].pixel_um
    filtered = lambda: [fwdfit.paganin_filter_1d(s.T, pixel, tau) for s, tau in zip(sims, taus)]
    seconds = _timed(filtered, repeats)
    return {"time_ms": 1e3 * seconds, "rms_T_filtered_vs_T_att": _rms(filtered(), converged_att)}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true", help="small sweep (CI smoke run)")
    args = parser.parse_args()
    accuracies = [1e-2, 1e-3] if args.quick else [3e-2, 1e-2, 3e-3, 1e-3, 3e-4, 1e-4, 3e-5]
    ray_counts = [1e4, 1e5] if args.quick else [1e4, 1e5, 1e6, 4e6]
    repeats = 3 if args.quick else 10
    record = {"default_accuracy": DEFAULT, "cases": {}}
    for label, path in CASES.items():
        print(label, flush=True)
        scene = fwdfit.load_scene(path)
        converged = fwdfit.simulate(scene, 1e-5)
        shared = [np.genfromtxt(path.parent / f"{p.name}.csv", delimiter=",", names=True)["T"]
                  for p in scene.profiles]
        record["cases"][label] = {
            "scene": str(path.relative_to(ROOT)),
            "model": model_sweep(scene, accuracies, [c.T for c in converged], shared, repeats),
            "reference": reference_sweep(scene, [int(r) for r in ray_counts], [c.T for c in converged]),
            "paganin": paganin_row(scene, [c.T_att for c in converged], repeats),
        }
    record["machine"] = {"device": str(jax.devices()[0]), "jax": jax.__version__}
    out = results_dir(args.quick) / "speed_vs_error.json"
    out.write_text(json.dumps(record, indent=2) + "\n")
    plot(record, out.with_suffix(".png"))
    print(f"wrote {out}")


def plot(record: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(record["cases"]), figsize=(11, 4.2), sharey=True)
    for ax, (label, case) in zip(np.atleast_1d(axes), record["cases"].items()):
        model, reference = case["model"], case["reference"]
        ax.loglog([r["time_ms"] for r in model], [r["rms_vs_converged"] for r in model], "o-", label="fwdfit model")
        for r in model:
            ax.annotate(f"{r['accuracy']:.0e}", (r["time_ms"], r["rms_vs_converged"]), fontsize=7,
                        textcoords="offset points", xytext=(4, 4))
        default = [r for r in model if r["accuracy"] == record["default_accuracy"]]
        ax.loglog([r["time_ms"] for r in default], [r["rms_vs_converged"] for r in default], "*", ms=16,
                  color="C3", label="default (accuracy 1e-3)")
        ax.loglog([r["time_ms"] for r in reference], [r["rms_vs_converged"] for r in reference], "s--",
                  label="exact reference (Monte Carlo)")
        ax.loglog([case["paganin"]["time_ms"]], [case["paganin"]["rms_T_filtered_vs_T_att"]], "^", ms=10,
                  label="Paganin filter (error of T_att)")
        ax.set_title(label)
        ax.set_xlabel("time per evaluation, all profiles (ms)")
        ax.grid(True, which="both", alpha=0.3)
    np.atleast_1d(axes)[0].set_ylabel("RMS error in T")
    np.atleast_1d(axes)[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()

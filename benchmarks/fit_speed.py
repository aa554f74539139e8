"""Fit speed: the joint Al-block fit, and fit time against profiles, layers and pixels.

The headline case is the joint fit of the Al block (1000 µm x 2 mm, tilt 0.24°,
centre 3 µm) to 10 BOA white-beam distances (1.1 to 34.4 mm) and 4 ICON lines
(2.7 to 4.6 Å at 1.1 mm), 1000 pixels of 2.4 µm each (±1200 µm, as the McStas
profiles), five free parameters (tilt, centre, thickness, SLD, mu). Then sweeps:
the number of profiles (1 to 14), of layers (Al; oxide | Al | oxide; the
five-layer anodic oxide, every distinct layer's thickness, SLD and mu free) and of
pixels per profile.

Data: ``fwdfit.simulate`` at the truth plus 1 % Gaussian noise (T_err = 0.01); the
fit starts 10 % away in every layer value, at tilt 0.20° and centre 0. Each case runs
in a fresh process: compile time (``fwdfit.Fitter``'s programs), fit time after
compilation, steps, peak memory (the process's maximum resident set) and the fitted
values against the truth. The joint case is also run as the plain command
(``fwdfit fit start.toml --out DIR`` in a fresh process), cold and warm.

    python benchmarks/fit_speed.py [--quick]

Writes benchmarks/results/fit_speed.{json,png} (``--quick``: one small case, to
benchmarks/results/quick/).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

from _results import results_dir, run_command
from _scenes import instruments, spectra

BOA_MM = (1.1, 4.8, 8.5, 12.2, 15.9, 19.6, 23.3, 27.0, 30.7, 34.4)
ICON_A = (2.7, 3.2, 4.0, 4.6)
NOISE = 0.01
PIXEL_UM = 2.4
# name: (thickness µm, SLD 1e-6/Å², mu 1/m); stacks are listed left to right
LAYERS = {"Al": (1000.0, 2.078, 9.059), "oxide1": (160.0, 3.304, 24.0), "oxide2": (80.0, 3.518, 12.0)}
STACKS = {1: ["Al"], 3: ["oxide1", "Al", "oxide1"], 5: ["oxide2", "oxide1", "Al", "oxide1", "oxide2"]}


def profile_list(n_profiles: int) -> list[tuple[str, float, str]]:
    """(name, distance_mm, spectrum) of n profiles: BOA and ICON interleaved, the joint set at 14."""
    boa = [(f"boa_d{d:04.1f}mm", d, "white") for d in BOA_MM]
    icon = [(f"icon_l{l}A", 1.1, f"l{l}") for l in ICON_A]
    order = [boa[0], icon[-1], boa[4], icon[0], boa[9], boa[2], icon[1], boa[7], boa[1], icon[2],
             boa[3], boa[5], boa[6], boa[8]]
    return order[:n_profiles]


def scene(case: dict, truth: bool, files: dict | None = None):
    """The scene of a case at the truth or at the start (+10 %), measured (``files``) or not."""
    import fwdfit

    factor = 1.0 if truth else 1.1
    half_um = case["half_width_um"]
    layers = {}
    for name in STACKS[case["layers"]]:
        if name in layers:
            layers[f"{name}_right"] = layers[name].tied(f"{name}_right")
        else:
            layers[name] = fwdfit.Layer(name, *(factor * value for value in LAYERS[name]))
    x_um = fwdfit.pixel_grid(-half_um, half_um, PIXEL_UM)
    profiles = tuple(fwdfit.Profile(name, distance, spectrum, "" if spectrum == "white" else "icon", x_um,
                                    file=files and files[name])
                     for name, distance, spectrum in profile_list(case["profiles"]))
    vary = ["sample.tilt_deg", "sample.centre_um"] + [
        f"layers.{name}.{key}" for name in dict.fromkeys(STACKS[case["layers"]])
        for key in ("thickness_um", "sld_e6_per_A2", "mu_per_m")]
    return fwdfit.Scene(
        sample=fwdfit.Sample(depth_mm=2.0, tilt_deg=0.24 if truth else 0.20, centre_um=3.0 if truth else 0.0,
                             layers=tuple(layers.values())),
        instruments=instruments(PIXEL_UM), spectra=spectra({f"l{l}": l for l in ICON_A}),
        profiles=profiles, fit=fwdfit.FitSpec(tuple(vary)))


def run_case(case: dict) -> dict:
    """Make the data, compile, fit; in this (fresh) process."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    import fwdfit

    folder = Path(tempfile.mkdtemp(prefix="fit_speed_"))
    truth_scene = scene(case, truth=True)
    rng = np.random.default_rng(0)
    files = {}
    for p in fwdfit.simulate(truth_scene):
        T = p.T + rng.normal(0.0, NOISE, p.T.shape)
        files[p.name] = folder / f"{p.name}.csv"
        np.savetxt(files[p.name], np.c_[p.x_um, T, np.full_like(T, NOISE)], delimiter=",",
                   header="x_um,T,T_err", comments="")
    scene_path = fwdfit.save_scene(scene(case, truth=False, files=files), folder / "start.toml")
    start_scene = fwdfit.load_scene(scene_path)
    truth = {"sample.tilt_deg": 0.24, "sample.centre_um": 3.0}
    for name in STACKS[case["layers"]]:
        for key, value in zip(("thickness_um", "sld_e6_per_A2", "mu_per_m"), LAYERS[name]):
            truth[f"layers.{name}.{key}"] = value
    start = time.perf_counter()
    fitter = fwdfit.Fitter(start_scene)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = fitter()
    pulls = {n: (v - truth[n]) / e for n, v, e in zip(result.names, result.values, result.errors)}
    return {**case, "pixels": int(sum(len(p.x_um) for p in start_scene.profiles)),
            "free_parameters": len(result.names), "compile_s": fitter.compile_time_s,
            "fit_s": result.wall_time_s, "total_s": time.perf_counter() - start,
            "steps": result.n_steps, "converged": result.converged, "chi2_reduced": result.chi2_reduced,
            "max_abs_pull": float(max(abs(v) for v in pulls.values())),
            "thickness_error_um": float(abs(result["layers.Al.thickness_um"][0] - 1000.0)),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "scene": str(scene_path)}


def cases(quick: bool) -> list[dict]:
    if quick:
        return [{"label": "quick", "profiles": 1, "layers": 1, "half_width_um": 300.0}]
    joint = {"label": "joint 10 BOA + 4 ICON", "profiles": 14, "layers": 1, "half_width_um": 1200.0}
    profiles = [{"label": f"profiles {n}", "profiles": n, "layers": 1, "half_width_um": 700.0}
                for n in (1, 4, 14)]
    # ±960 µm: the five-layer stack's outer faces lie at ±740 µm
    layers = [{"label": f"layers {n}", "profiles": 3, "layers": n, "half_width_um": 960.0} for n in (1, 3, 5)]
    pixels = [{"label": f"half width {w:g} um", "profiles": 3, "layers": 1, "half_width_um": w}
              for w in (600.0, 2400.0)]
    return [joint] + profiles + layers + pixels


def plot(record: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = record["cases"]
    sweeps = [("profiles", "profiles", "number of profiles (±700 µm, Al)"),
              ("layers", "layers", "number of layers (3 profiles, ±960 µm)"),
              ("half width", "pixels", "pixels in all profiles (3 profiles, Al)")]
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6), dpi=100)
    for ax, (prefix, key, xlabel) in zip(axes, sweeps):
        chosen = sorted((r for r in rows if r["label"].startswith(prefix)
                         or (prefix == "half width" and r["label"] == "layers 1")), key=lambda r: r[key])
        x = [r[key] for r in chosen]
        ax.plot(x, [r["fit_s"] for r in chosen], "o-", label="fit (after compilation)")
        ax.plot(x, [r["compile_s"] for r in chosen], "s--", label="compilation")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("wall time (s)")
        ax.grid(alpha=0.3)
    joint = next((r for r in rows if r["label"].startswith("joint")), None)
    if joint:
        axes[0].plot([joint["profiles"]], [joint["fit_s"]], "*", ms=12, color="C3",
                     label=f"joint, ±1200 µm: {joint['fit_s']:.1f} s")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"fwdfit fit speed, {record['machine']['device']}, {record['machine']['cpus']} CPU cores",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one small case (CI smoke run)")
    parser.add_argument("--only", help="run only the cases whose label contains one of these "
                        "comma-separated words")
    parser.add_argument("--case", help=argparse.SUPPRESS)  # JSON: run one case in this process
    args = parser.parse_args()
    if args.case:
        print(json.dumps(run_case(json.loads(args.case))))
        return
    rows = []
    chosen = [c for c in cases(args.quick)
              if not args.only or any(word in c["label"] for word in args.only.split(","))]
    for case in chosen:
        out = subprocess.run([sys.executable, __file__, "--case", json.dumps(case)], capture_output=True,
                             text=True, check=True)
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
        r = rows[-1]
        if r["label"].startswith("joint"):  # the plain command too, cold and warm, as a user runs it
            folder = Path(r["scene"]).parent
            for kind in ("cold", "warm"):
                r[f"command_{kind}"] = run_command(Path(r["scene"]), folder / kind, folder / "cache")
            print(f"{r['label']}: fwdfit fit cold {r['command_cold']['wall_s']} s, "
                  f"warm {r['command_warm']['wall_s']} s", flush=True)
        print(f"{r['label']:<24} {r['pixels']:6d} px {r['free_parameters']:3d} free  compile {r['compile_s']:6.1f} s"
              f"  fit {r['fit_s']:6.1f} s  {r['steps']:3d} steps  {r['peak_rss_mb']:6.0f} MB  "
              f"chi2_red {r['chi2_reduced']:.3f}  max |pull| {r['max_abs_pull']:.2f}", flush=True)
    import jax

    record = {"description": __doc__.split("\n\n")[1].replace("\n", " "),
              "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                          "device": str(jax.devices()[0]), "jax": jax.__version__,
                          "python": platform.python_version()},
              "cases": rows}
    results = results_dir(args.quick)
    (results / "fit_speed.json").write_text(json.dumps(record, indent=1) + "\n")
    plot(record, results / "fit_speed.png")
    print(f"wrote {results / 'fit_speed.json'}")


if __name__ == "__main__":
    main()

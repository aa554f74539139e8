"""Benchmark: the paper's Paganin-filter comparison, made reproducible.

For the Al block (ray tracer ``tests/data/raytrace/al_boa_tilt0``; McStas BOA and ICON
scenes in ``tests/data/mcstas``, tilt 0 and 0.24 degrees) and the five-layer oxide
sample (ray tracer ``oxide5_boa``; and an ICON variant of it, "measured" here with
``fwdfit.simulate`` plus 0.5 % Gaussian noise, fixed seed), every profile is filtered
with Al's constants (as the paper did for both samples) and compared with the true
attenuation-only profile T_att of the same source:

(a) Paganin with the tabulated SLD (b_factor 1);
(b) Paganin with the b_factor, on a log grid 0.01..200, that minimises the RMS of
    T_filtered - T_att over the pixels within +-50 um of any interface (where the
    refraction peaks are), reported per profile and as medians;
(c) the forward-model fit's T_att (hook ``fit_attenuation_only``; skipped with a
    message while ``fwdfit.fit`` is not importable).

Also the largest |T_filtered - T_att| near the interfaces (the residual peaks), and
the 10-90 % rise distance of the outer (air/sample) edges of T_att and of the
filtered profiles. Writes ``benchmarks/results/paganin_comparison.{json,md,png}``.

    PYTHONPATH=src python3 benchmarks/paganin_comparison.py [--skip-fit]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import fwdfit  # noqa: E402
from fwdfit import load_scene, simulate  # noqa: E402
from fwdfit.paganin import paganin_filter_1d  # noqa: E402
from fwdfit.paganin import paganin_layer, paganin_profiles, profile_tau_um2  # noqa: E402
from fwdfit.scene import read_columns, write_columns  # noqa: E402
from _results import results_dir  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"
MATERIAL = "Al"  # the paper used Al's constants for both samples
# 20 points per decade. The brief asked for 1..200; the grid reaches down to 0.01 because
# the optimum lies below 1 for most profiles (for the oxide with Al's constants near 0.05).
B_GRID = np.geomspace(0.01, 200.0, 87)
EDGE_WINDOW_UM = 50.0
NOISE_SIGMA = 0.005  # absolute, in T (0.5 % of the open beam)
# T_err written for the Monte Carlo profiles (zero in air, where sample and open runs
# share their rays) is raised to this floor, the model's accuracy: weights for the fit (c).
T_ERR_FLOOR = 1e-3
SEED = 20240611
OXIDE_VARY = ["sample.centre_um", "layers.Al.mu_per_m", "layers.Al.sld_e6_per_A2",
              "layers.oxide1_left.thickness_um", "layers.oxide1_left.mu_per_m",
              "layers.oxide1_left.sld_e6_per_A2", "layers.oxide2_left.thickness_um",
              "layers.oxide2_left.mu_per_m", "layers.oxide2_left.sld_e6_per_A2"]
AL_VARY = ["sample.centre_um", "sample.tilt_deg", "layers.Al.mu_per_m", "layers.Al.sld_e6_per_A2"]
ICON_WAVELENGTHS_A = (2.7, 3.2, 4.0, 4.6)


@dataclasses.dataclass
class Case:
    """One measured scene (written to a temp folder) with its true T_att per profile."""

    label: str
    sample: str  # "Al" or "oxide"
    source: str
    scene: Path
    T_att: dict[str, np.ndarray]


# ---------------------------------------------------------------- scenes

def _measured_scene(scene: fwdfit.Scene, measured: dict, folder: Path, vary: list[str]) -> Path:
    """Save ``folder/scene.toml``: ``scene`` with every profile read from ``<name>.csv`` (x_um, T, T_err)."""
    folder.mkdir(parents=True)
    profiles = []
    for profile in scene.profiles:
        file = folder / f"{profile.name}.csv"
        write_columns(file, measured[profile.name])
        profiles.append(dataclasses.replace(profile, x_um=measured[profile.name]["x_um"], file=file))
    return fwdfit.save_scene(dataclasses.replace(scene, profiles=tuple(profiles), fit=fwdfit.FitSpec(tuple(vary))),
                             folder / "scene.toml")


def raytrace_case(name: str, label: str, sample: str, vary, tmp: Path) -> Case:
    source = DATA / "raytrace" / name
    scene = load_scene(source / "scene.toml")
    measured, truth = {}, {}
    for profile in scene.profiles:
        table = read_columns(source / f"{profile.name}.csv", ["x_um", "T", "T_err", "T_att"])
        measured[profile.name] = {"x_um": table["x_um"], "T": table["T"],
                                  "T_err": np.maximum(table["T_err"], T_ERR_FLOOR)}
        truth[profile.name] = table["T_att"]
    return Case(label, sample, "ray tracer", _measured_scene(scene, measured, tmp / name, vary), truth)


def mcstas_case(scene_name: str, label: str, tmp: Path) -> Case:
    source = DATA / "mcstas"
    scene = load_scene(source / scene_name)
    measured, truth = {}, {}
    for profile in scene.profiles:
        table = read_columns(source / f"{profile.name}.csv", ["x_um", "T", "T_err"])
        att = read_columns(source / f"{profile.name}_attenuation_only.csv", ["x_um", "T"])
        assert np.allclose(att["x_um"], table["x_um"])
        measured[profile.name] = {"x_um": table["x_um"], "T": table["T"],
                                  "T_err": np.maximum(table["T_err"], T_ERR_FLOOR)}
        truth[profile.name] = att["T"]
    path = _measured_scene(scene, measured, tmp / Path(scene_name).stem, AL_VARY)
    return Case(label, "Al", "McStas", path, truth)


def oxide_icon_case(tmp: Path) -> Case:
    """The oxide sample at ICON (1.1 mm, four lines): simulated, plus Gaussian noise."""
    oxide = load_scene(DATA / "raytrace" / "oxide5_boa" / "scene.toml")
    x_um = fwdfit.pixel_grid(-912.0, 912.0, 2.4)
    scene = dataclasses.replace(
        oxide, instruments={"": fwdfit.Instrument("circular", 40.0, 5.5, 2.4)},
        spectra={f"l{lam}A": fwdfit.GaussianLine(lam, 0.15) for lam in ICON_WAVELENGTHS_A},
        profiles=tuple(fwdfit.Profile(f"l{lam}A", 1.1, f"l{lam}A", "", x_um) for lam in ICON_WAVELENGTHS_A))
    rng = np.random.default_rng(SEED)
    measured, truth = {}, {}
    for p in simulate(scene):
        noisy = p.T + NOISE_SIGMA * rng.standard_normal(p.T.shape)
        measured[p.name] = {"x_um": p.x_um, "T": noisy, "T_err": np.full_like(noisy, NOISE_SIGMA)}
        truth[p.name] = p.T_att
    path = _measured_scene(scene, measured, tmp / "oxide5_icon", OXIDE_VARY)
    return Case("oxide, ICON, fwdfit.simulate + 0.5 % noise", "oxide",
                "fwdfit.simulate + noise", path, truth)


# ------------------------------------------------- (c) forward-model fit hook


def fit_attenuation_only(scene_path: Path) -> dict[str, np.ndarray]:
    """HOOK (c): the forward-model fit's attenuation-only profile, {profile name: T_att_fit}.

    Fits the scene's ``[fit] vary`` parameters to all of its profiles at once with the
    project's fitting module and returns each profile's fitted T_att. The scenes here
    start from the true parameters; a fair test starts elsewhere (``n_starts``).
    """
    from fwdfit import fit

    result = fit(scene_path)
    return {p.name: np.asarray(p.T_att) for p in result.profiles}


# ---------------------------------------------------------------- metrics

def _boundaries_um(scene) -> np.ndarray:
    """x of every layer boundary at the sample's mid-depth (tilt shifts them by < 5 um here)."""
    widths = [layer.thickness_um for layer in scene.sample.layers]
    return scene.sample.centre_um - sum(widths) / 2 + np.concatenate([[0.0], np.cumsum(widths)])


def _outer_layer_centres_um(scene) -> tuple[float, float]:
    """x of the centres of the outermost layers: the plateaus the outer edges rise to."""
    edges = _boundaries_um(scene)
    return 0.5 * (edges[0] + edges[1]), 0.5 * (edges[-2] + edges[-1])


def _rms(values) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


def _peak(T, T_att, near) -> float:
    """Largest |T - T_att| near the interfaces: what is left of the refraction peaks."""
    return float(np.max(np.abs(T[near] - T_att[near])))


def _edge_width_um(x_um, T, T_att, plateau_um: float, side: str) -> float | None:
    """10-90 % rise distance of an outer edge of T, levels from T_att (air and plateau).

    Walking from the profile's end on ``side`` towards the plateau point: x90 is the
    first crossing of the 90 % level, x10 the last crossing of the 10 % level before it
    (so noise out in the air does not count), both linearly interpolated between
    pixels. None if T never reaches the 90 % level.
    """
    if side == "right":
        x_um, T, T_att, plateau_um = -x_um[::-1], T[::-1], T_att[::-1], -plateau_um
    inside = int(np.searchsorted(x_um, plateau_um))
    air = float(np.mean(T_att[:20]))
    plateau = float(np.mean(T_att[max(inside - 2, 0):inside + 3]))
    level10, level90 = air - 0.1 * (air - plateau), air - 0.9 * (air - plateau)
    below = np.flatnonzero(T[:inside + 1] <= level90)
    if below.size == 0 or below[0] == 0:
        return None
    i90 = below[0]
    above = np.flatnonzero(T[:i90] > level10)
    if above.size == 0:
        return None
    i10 = above[-1] + 1  # first pixel at or below the 10 % level after the last one above it

    def crossing(i, level):
        t = (T[i - 1] - level) / (T[i - 1] - T[i])
        return x_um[i - 1] + t * (x_um[i] - x_um[i - 1])

    return float(crossing(i90, level90) - crossing(i10, level10))


def _widths(x_um, T, T_att, plateaus) -> dict:
    return {side: _edge_width_um(x_um, T, T_att, plateau, side)
            for side, plateau in zip(("left", "right"), plateaus)}


def _filtered_scan(scene, profile, layer) -> list[np.ndarray | None]:
    """T_filtered for every b_factor of B_GRID; None where tau <= 0 (divergence wins)."""
    step = float(np.median(np.diff(profile.x_um)))
    scan = []
    for b in B_GRID:
        tau = profile_tau_um2(scene, profile, layer, b_factor=b)
        scan.append(paganin_filter_1d(profile.T, step, tau) if tau > 0 else None)
    return scan


def evaluate(case: Case, fitted: dict[str, np.ndarray] | None) -> dict:
    """Per-profile RMS errors, best b_factor and edge widths of one case."""
    scene = load_scene(case.scene)
    layer = paganin_layer(scene, MATERIAL)
    tabulated = paganin_profiles(scene, material=MATERIAL, b_factor=1.0)  # what `fwdfit paganin` writes
    boundaries = _boundaries_um(scene)
    plateaus = _outer_layer_centres_um(scene)
    rows = []
    for profile, b1 in zip(scene.profiles, tabulated):
        x, T, T_att = profile.x_um, profile.T, case.T_att[profile.name]
        scan = _filtered_scan(scene, profile, layer)
        near = np.min(np.abs(x[:, None] - boundaries[None, :]), axis=1) <= EDGE_WINDOW_UM
        edge_rms = np.array([np.inf if f is None else _rms(f[near] - T_att[near]) for f in scan])
        whole_rms = np.array([np.inf if f is None else _rms(f - T_att) for f in scan])
        best = int(np.argmin(edge_rms))
        best_whole = int(np.argmin(whole_rms))
        spectrum = scene.spectra[profile.spectrum]
        row = {
            "profile": profile.name, "distance_mm": profile.distance_mm,
            "mean_wavelength_A": round(spectrum.mean_wavelength_A, 4),
            "tau_b1_um2": b1.tau_um2,
            "tau_best_um2": profile_tau_um2(scene, profile, layer, b_factor=B_GRID[best]),
            "rms_edge": {"unfiltered": _rms(T[near] - T_att[near]),
                         "paganin_b1": _rms(b1.T_filtered[near] - T_att[near]),
                         "paganin_best_b": edge_rms[best]},
            "rms_whole": {"unfiltered": _rms(T - T_att), "paganin_b1": _rms(b1.T_filtered - T_att),
                          "paganin_best_b": whole_rms[best]},
            "max_abs_edge": {"unfiltered": _peak(T, T_att, near),
                             "paganin_b1": _peak(b1.T_filtered, T_att, near),
                             "paganin_best_b": _peak(scan[best], T_att, near)},
            "best_b_factor": float(B_GRID[best]),
            "best_b_factor_whole_profile": float(B_GRID[best_whole]),
            "rms_whole_at_its_best_b": whole_rms[best_whole],
            "best_b_at_grid_end": best in (0, len(B_GRID) - 1),
            "edge_width_10_90_um": {
                "T_att": _widths(x, T_att, T_att, plateaus),
                "paganin_b1": _widths(x, b1.T_filtered, T_att, plateaus),
                "paganin_best_b": _widths(x, scan[best], T_att, plateaus),
            },
            "curves": {"x_um": x, "T": T, "T_att": T_att, "paganin_b1": b1.T_filtered,
                       "paganin_best_b": scan[best]},
        }
        if fitted is not None:
            T_fit = fitted[profile.name]
            row["rms_edge"]["forward_model_fit"] = _rms(T_fit[near] - T_att[near])
            row["rms_whole"]["forward_model_fit"] = _rms(T_fit - T_att)
            row["max_abs_edge"]["forward_model_fit"] = _peak(T_fit, T_att, near)
            row["edge_width_10_90_um"]["forward_model_fit"] = _widths(x, T_fit, T_att, plateaus)
        rows.append(row)
    return {"label": case.label, "sample": case.sample, "source": case.source,
            "material_constants": MATERIAL, "profiles": rows,
            "median_best_b_factor": float(np.median([r["best_b_factor"] for r in rows]))}


# ---------------------------------------------------------------- outputs

def _mean_width(widths: dict) -> float | None:
    values = [w for w in widths.values() if w is not None]
    return float(np.mean(values)) if len(values) == len(widths) else None


def _fmt(value, digits=3) -> str:
    if value is None:
        return "n/a"
    return f"{value:.{digits}g}" if abs(value) < 1e4 else f"{value:.3e}"


def markdown(results: dict) -> str:
    with_fit = results["forward_model_fit"] == "included"
    lines = ["# Paganin-type filter vs the true attenuation-only profile", "",
             f"Generated by `benchmarks/paganin_comparison.py` ({results['wall_time_s']:.0f} s). "
             f"Filter constants: layer `{MATERIAL}` for every sample (as in the paper), tau at the "
             "spectrum's mean wavelength. RMS of (profile - T_att): *edge* over pixels within "
             f"+-{EDGE_WINDOW_UM:g} um of any interface, *whole* over the profile; *peak*: the "
             "largest |profile - T_att| within that window. Best b: the b_factor on a log grid "
             f"{B_GRID[0]:g}..{B_GRID[-1]:g} ({len(B_GRID)} points) with the smallest edge RMS "
             "(a `*` marks the grid's end). Edge width: 10-90 % rise of the outer edges "
             "(mean of left and right, um; levels: T_att in air and at the centre of the outermost "
             "layer, i.e. Al for the block and the 80 um oxide2 layer for the oxide sample; "
             "n/a: the profile never reaches the 90 % level).", ""]
    if not with_fit:
        lines += ["Forward-model fit (c): left out of this run (`--skip-fit` or `--quick`).", ""]
    head = ["profile", "Δ mm", "λ̄ Å", "tau(b=1) um²", "edge RMS raw", "edge RMS b=1",
            "edge RMS best", "whole RMS b=1", "whole RMS best", "peak raw", "peak b=1",
            "peak best", "best b", "width T_att", "width b=1", "width best"]
    if with_fit:
        head[7:7] = ["edge RMS fit"]
        head.append("width fit")
    for case in results["cases"]:
        lines += [f"## {case['label']}", "",
                  f"median best b_factor: **{case['median_best_b_factor']:.3g}**", "",
                  "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for r in case["profiles"]:
            w = {k: _mean_width(v) for k, v in r["edge_width_10_90_um"].items()}
            cells = [r["profile"], f"{r['distance_mm']:g}", f"{r['mean_wavelength_A']:.2f}",
                     _fmt(r["tau_b1_um2"], 4), _fmt(r["rms_edge"]["unfiltered"]),
                     _fmt(r["rms_edge"]["paganin_b1"]), _fmt(r["rms_edge"]["paganin_best_b"]),
                     _fmt(r["rms_whole"]["paganin_b1"]), _fmt(r["rms_whole"]["paganin_best_b"]),
                     _fmt(r["max_abs_edge"]["unfiltered"]), _fmt(r["max_abs_edge"]["paganin_b1"]),
                     _fmt(r["max_abs_edge"]["paganin_best_b"]),
                     f"{r['best_b_factor']:.3g}{'*' if r['best_b_at_grid_end'] else ''}",
                     _fmt(w["T_att"]), _fmt(w["paganin_b1"]), _fmt(w["paganin_best_b"])]
            if with_fit:
                cells[7:7] = [_fmt(r["rms_edge"]["forward_model_fit"])]
                cells.append(_fmt(w["forward_model_fit"]))
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    summary = results["summary"]
    lines += ["## Summary", "",
              f"median best b_factor over all {summary['n_profiles']} profiles: "
              f"**{summary['median_best_b_factor']:.3g}** (Al block {summary['median_best_b_al']:.3g}, "
              f"oxide {summary['median_best_b_oxide']:.3g}; the paper needed about 40).", "",
              "tau scales as SLD / mu, and the filter is exact for a homogeneous object with "
              "the data's own SLD and mu. SLD / mu is 1.5 for Al (mu = 1.39 /m) but 0.14 and "
              "0.29 for oxide1 and oxide2 (1e-6 Å^-2 m): filtered with Al's constants, the "
              "oxide sample needs b of order 0.1.",
              "Edge widths are indicative where the air-to-layer step is small (Al block: "
              "0.003 in T with the ray tracer's mu = 1.39 /m, 0.024 with McStas'): residual "
              "peaks or noise of that size move the 10 % and 90 % crossings.", ""]
    return "\n".join(lines)


def plot(results: dict, path: Path) -> None:
    """Oxide sample: BOA at 1.1 / 12.2 / 34.4 mm (whole and left edge) and ICON lines."""
    cases = {c["label"]: c for c in results["cases"]}
    boa = cases["oxide, BOA, ray tracer"]["profiles"]
    icon = cases["oxide, ICON, fwdfit.simulate + 0.5 % noise"]["profiles"]
    fig, axes = plt.subplots(1, 3, figsize=(16, 7), gridspec_kw={"width_ratios": [1.4, 1, 1]})
    styles = [("T", "data", dict(color="0.6", lw=1.0)),
              ("T_att", "true T_att", dict(color="k", lw=1.4)),
              ("paganin_b1", "Paganin, b = 1", dict(color="tab:blue", lw=1.4, ls=":")),
              ("paganin_best_b", "Paganin, best b", dict(color="tab:red", lw=1.2, ls="--"))]
    panels = [(axes[0], boa, None, "distance_mm", "Δ = {:g} mm", "(a) oxide, BOA, ray tracer"),
              (axes[1], boa, (-780, -380), "distance_mm", "Δ = {:g} mm", "(b) left edge of (a)"),
              (axes[2], icon, (-780, -380), "mean_wavelength_A", "λ = {:g} Å",
               "(c) oxide, ICON 1.1 mm, simulated + 0.5 % noise")]
    step = 0.4
    for ax, rows, xlim, key, tag, title in panels:
        for k, r in enumerate(rows):
            c = r["curves"]
            for name, label, style in styles:
                ax.plot(c["x_um"], np.asarray(c[name]) + step * k, label=label if k == 0 else None,
                        **style)
            x_text = xlim[0] + 5 if xlim else c["x_um"][0]
            ax.text(x_text, 1.16 + step * k, tag.format(r[key]) + f", best b = {r['best_b_factor']:.2g}",
                    fontsize=9)
        if xlim:
            ax.set_xlim(*xlim)
        ax.set_ylim(0.65, 1.25 + step * (len(rows) - 1))
        ax.set_xlabel("x (µm)")
        ax.set_title(title, fontsize=10)
    axes[0].set_ylabel(f"transmission T (profiles offset by {step:g})")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=4, fontsize=10)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    fig.savefig(path, dpi=130)
    plt.close(fig)


def _plain(value):
    """JSON-ready: numpy to lists, floats rounded to 6 significant digits."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(f"{float(value):.6g}")
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--skip-fit", action="store_true", help="leave out (c), the forward-model fit")
    parser.add_argument("--quick", action="store_true", help="first case, no fit (CI smoke run)")
    args = parser.parse_args()
    start = time.perf_counter()
    use_fit = not (args.skip_fit or args.quick)
    RESULTS = results_dir(args.quick)
    with tempfile.TemporaryDirectory() as folder:
        tmp = Path(folder)
        cases = [
            raytrace_case("al_boa_tilt0", "Al, BOA, ray tracer", "Al", AL_VARY, tmp),
            mcstas_case("scene_boa_tilt0.00.toml", "Al, BOA, McStas, tilt 0", tmp),
            mcstas_case("scene_boa_tilt0.24.toml", "Al, BOA, McStas, tilt 0.24°", tmp),
            mcstas_case("scene_icon_tilt0.00.toml", "Al, ICON 1.1 mm, McStas, tilt 0", tmp),
            mcstas_case("scene_icon_tilt0.24.toml", "Al, ICON 1.1 mm, McStas, tilt 0.24°", tmp),
            raytrace_case("oxide5_boa", "oxide, BOA, ray tracer", "oxide", OXIDE_VARY, tmp),
            oxide_icon_case(tmp),
        ]
        evaluated = []
        for case in cases[:1 if args.quick else None]:
            fitted = fit_attenuation_only(case.scene) if use_fit else None
            evaluated.append(evaluate(case, fitted))
            print(f"{case.label}: median best b_factor {evaluated[-1]['median_best_b_factor']:.3g}")
    rows = [(c["sample"], r) for c in evaluated for r in c["profiles"]]
    best = lambda sample=None: float(np.median([r["best_b_factor"] for s, r in rows
                                                 if sample in (None, s)]))
    results = {
        "benchmark": "paganin_comparison",
        "settings": {"material_constants": MATERIAL, "mode": "mean_wavelength",
                     "b_grid": [float(B_GRID[0]), float(B_GRID[-1]), len(B_GRID)],
                     "edge_window_um": EDGE_WINDOW_UM, "noise_sigma": NOISE_SIGMA, "seed": SEED},
        "forward_model_fit": "included" if use_fit else "left out (--skip-fit or --quick)",
        "cases": evaluated,
        "summary": {"n_profiles": len(rows), "median_best_b_factor": best(),
                    "median_best_b_al": best("Al"), "median_best_b_oxide": best("oxide")},
        "wall_time_s": time.perf_counter() - start,
        "machine": {"python": platform.python_version(), "cpu_count": os.cpu_count(),
                    "platform": platform.platform()},
    }
    plot(results, RESULTS / "paganin_comparison.png")
    (RESULTS / "paganin_comparison.md").write_text(markdown(results))
    for case in results["cases"]:
        for r in case["profiles"]:
            r.pop("curves")
    (RESULTS / "paganin_comparison.json").write_text(json.dumps(_plain(results), indent=1) + "\n")
    print(f"wrote {RESULTS}/paganin_comparison.{{json,md,png}} in {results['wall_time_s']:.0f} s")


if __name__ == "__main__":
    main()

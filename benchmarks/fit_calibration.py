"""Are the fit's 1-sigma errors honest? Coverage over repeated noise draws.

The Al block (1000 µm x 2 mm, Al at 2.70 g/cm3, tilt 0.24°, centre 3 µm), measured
at BOA 1.1 and 8.5 mm (white beam) and ICON 4.6 Å (1.1 mm), ±700 µm each. The data
are the model itself at the truth (``fwdfit.simulate``) plus 1 % Gaussian noise with
T_err = 0.01, so only noise, not model error, moves the fitted values. Every draw is
fitted from the same start (~10 % away from the truth in every parameter) with the
full coarse-to-fine schedule of ``fwdfit.fit``.

For each parameter the script reports the fraction of draws whose truth lies within
1 sigma (expected 68.3 %) and 2 sigma (95.4 %), the mean and the standard deviation
of the pulls (value - truth) / error (expected 0 and 1), and the ratio of the
empirical scatter of the values to the mean reported error (expected 1); and the
fraction of pixels (those where the band has a width) where the truth's T_att lies
inside the reported T_att ± T_att_err. A draw with a pull beyond 2.5 is refitted from
the truth, to tell a solver that stopped early (lower chi-square from the truth) from
an honest tail of the noise.

``fwdfit.fit`` compiles its solver anew on every call (tens of seconds), so the draws
reuse ONE ``fwdfit.Fitter``: only the data change between draws. The first two draws
are also fitted with ``fwdfit.fit``, which must give the same values; their compile
times are recorded.

    python benchmarks/fit_calibration.py [N_DRAWS] [TIME_LIMIT_S] [--quick]

Writes ``benchmarks/results/fit_calibration.json``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import platform
import sys
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
import optimistix as optx  # noqa: E402

import fwdfit  # noqa: E402
from _results import results_dir  # noqa: E402
from _scenes import instruments, spectra  # noqa: E402

NOISE = 0.01
AL = fwdfit.constants_from_formula("Al", 2.70)
TRUTH = {
    "sample.tilt_deg": 0.24,
    "sample.centre_um": 3.0,
    "layers.Al.thickness_um": 1000.0,
    "layers.Al.sld_e6_per_A2": AL.sld_e6_per_A2,
    "layers.Al.mu_per_m": AL.mu_per_m,
}
START = {
    "sample.tilt_deg": 0.20,
    "sample.centre_um": 0.0,
    "layers.Al.thickness_um": 1100.0,
    "layers.Al.sld_e6_per_A2": 0.9 * AL.sld_e6_per_A2,
    "layers.Al.mu_per_m": 1.1 * AL.mu_per_m,
}


def scene(values: dict) -> fwdfit.Scene:
    """The Al block at ``values`` (its free parameters), BOA at 1.1 and 8.5 mm, ICON 4.6 Å at 1.1 mm."""
    layer = fwdfit.Layer("Al", values["layers.Al.thickness_um"], values["layers.Al.sld_e6_per_A2"],
                         values["layers.Al.mu_per_m"], AL.mu_per_m_per_A)
    x_um = fwdfit.pixel_grid(-700.8, 700.8, 2.4)
    return fwdfit.Scene(
        sample=fwdfit.Sample(depth_mm=2.0, tilt_deg=values["sample.tilt_deg"], centre_um=values["sample.centre_um"],
                             layers=(layer,)),
        instruments=instruments(), spectra=spectra({"l46": 4.6}),
        profiles=(fwdfit.Profile("boa_d01.1mm", 1.1, "white", "", x_um),
                  fwdfit.Profile("boa_d08.5mm", 8.5, "white", "", x_um),
                  fwdfit.Profile("icon_l4.6A", 1.1, "l46", "icon", x_um)),
        fit=fwdfit.FitSpec(tuple(values)))


def main(n_draws: int = 40, time_limit_s: float = 900.0, quick: bool = False) -> dict:
    RESULTS = results_dir(quick)
    t_begin = time.perf_counter()
    truth_profiles = fwdfit.simulate(scene(TRUTH))
    start_scene = scene(START)
    base = dataclasses.replace(start_scene, profiles=tuple(
        dataclasses.replace(p, T=t.T.copy(), T_err=np.full_like(t.T, NOISE))
        for p, t in zip(start_scene.profiles, truth_profiles)), fit=fwdfit.FitSpec(tuple(START), {}))
    n_pixels = sum(len(p.x_um) for p in base.profiles)
    print(f"{len(base.profiles)} profiles, {n_pixels} pixels, {len(START)} free parameters", flush=True)

    def draw(seed):
        rng = np.random.default_rng(seed)
        return [t.T + rng.normal(0.0, NOISE, t.T.shape) for t in truth_profiles]

    t = time.perf_counter()
    compiled = fwdfit.Fitter(base)
    names = [p.name for p in compiled.free]
    truth = np.array([TRUTH[n] for n in names])
    print(f"compiled once: {compiled.compile_time_s:.1f} s (setup {time.perf_counter() - t:.1f} s)",
          flush=True)

    # The public fit() on the first two draws: same answer, and a fresh compile every call.
    public = []
    for seed in range(2):
        scene = dataclasses.replace(base, profiles=tuple(
            dataclasses.replace(p, T=T) for p, T in zip(base.profiles, draw(seed))))
        t = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = fwdfit.fit(scene)
        public.append({"seed": seed, "values": result.values.tolist(), "errors": result.errors.tolist(),
                       "chi2": result.chi2, "compile_time_s": result.compile_time_s,
                       "fit_time_s": result.wall_time_s, "call_time_s": time.perf_counter() - t})
        print(f"public fit() seed {seed}: call {public[-1]['call_time_s']:.1f} s, compile "
              f"{result.compile_time_s:.1f} s, solve {result.wall_time_s:.1f} s", flush=True)

    draws = []
    loop_start = time.perf_counter()
    for seed in range(n_draws):
        elapsed = time.perf_counter() - loop_start
        if draws and elapsed + elapsed / len(draws) > time_limit_s:
            print(f"time limit: stopping after {len(draws)} draws", flush=True)
            break
        data = draw(seed)
        t = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = compiled(data)
        call_time = time.perf_counter() - t
        pulls = (result.values - truth) / result.errors
        # T_att band: pixels where the band has a width (outside the sample T_att = 1 exactly)
        att_inside = [float(np.mean((np.abs(p.T_att - tp.T_att) <= p.T_att_err)[p.T_att_err > 1e-9]))
                      for p, tp in zip(result.profiles, truth_profiles)]
        # A pull beyond 2.5: is it the noise, or did the solver stop early? Refit from the truth.
        check = None
        if np.max(np.abs(pulls)) > 2.5:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                again = compiled(data, start=truth)
            check = {"chi2_from_truth": again.chi2, "chi2_minus_chi2_from_truth": result.chi2 - again.chi2,
                     "values_from_truth": again.values.tolist(),
                     "pulls_from_truth": ((again.values - truth) / again.errors).tolist()}
            print(f"          refit from the truth: chi2 lower by {result.chi2 - again.chi2:.4f}, pulls "
                  + " ".join(f"{p:+5.2f}" for p in check["pulls_from_truth"]), flush=True)
        draws.append({"seed": seed, "values": result.values.tolist(), "errors": result.errors.tolist(),
                      "pulls": pulls.tolist(), "chi2": result.chi2, "chi2_reduced": result.chi2_reduced,
                      "converged": result.converged, "steps": result.n_steps,
                      "solve_time_s": result.wall_time_s, "call_time_s": call_time,
                      "T_att_inside_1sigma": att_inside, "refit_from_truth": check})
        print(f"draw {seed:3d}: chi2_red {result.chi2_reduced:.4f} steps {result.n_steps:3d} "
              f"{call_time:5.1f} s  pulls " + " ".join(f"{p:+5.2f}" for p in pulls), flush=True)

    values = np.array([d["values"] for d in draws])
    errors = np.array([d["errors"] for d in draws])
    pulls = np.array([d["pulls"] for d in draws])
    n = len(draws)
    summary = {}
    for i, name in enumerate(names):
        inside1 = float(np.mean(np.abs(pulls[:, i]) < 1.0))
        summary[name] = {
            "truth": float(truth[i]),
            "coverage_1sigma": inside1,
            "coverage_1sigma_binomial_error": math.sqrt(0.683 * 0.317 / n),
            "coverage_2sigma": float(np.mean(np.abs(pulls[:, i]) < 2.0)),
            "mean_pull": float(pulls[:, i].mean()),
            "std_pull": float(pulls[:, i].std(ddof=1)) if n > 1 else None,
            "max_abs_pull": float(np.abs(pulls[:, i]).max()),
            "mean_value": float(values[:, i].mean()),
            "std_value": float(values[:, i].std(ddof=1)) if n > 1 else None,
            "mean_error": float(errors[:, i].mean()),
            "scatter_over_error": float(values[:, i].std(ddof=1) / errors[:, i].mean()) if n > 1 else None,
        }
    chi2 = np.array([d["chi2"] for d in draws])
    # Public fit() and the reused solver agree on the same data?
    agreement = [float(np.max(np.abs(np.array(p["values"]) - values[k]) / errors[k]))
                 for k, p in enumerate(public) if k < n]
    output = {
        "description": "coverage of the fit's 1-sigma errors over noise draws; data = fwdfit.simulate "
                       "at the truth + 1 % Gaussian noise (T_err = 0.01); Al block, BOA 1.1 and 8.5 mm, "
                       "ICON 4.6 A at 1.1 mm, +-700 um; same start every draw",
        "truth": TRUTH, "start": START, "n_draws": n, "n_pixels": n_pixels, "dof": n_pixels - len(names),
        "summary": summary,
        "all_parameters_within_1sigma": float(np.mean(np.all(np.abs(pulls) < 1.0, axis=1))),
        "chi2_reduced_mean": float(chi2.mean() / (n_pixels - len(names))),
        "chi2_reduced_std": float(chi2.std(ddof=1) / (n_pixels - len(names))) if n > 1 else None,
        "chi2_reduced_expected_std": math.sqrt(2.0 / (n_pixels - len(names))),
        "converged_fraction": float(np.mean([d["converged"] for d in draws])),
        "T_att_inside_1sigma_mean": float(np.mean([d["T_att_inside_1sigma"] for d in draws])),
        "timing": {
            "compile_once_s": compiled.compile_time_s,
            "mean_draw_s": float(np.mean([d["call_time_s"] for d in draws])),
            "mean_solve_s": float(np.mean([d["solve_time_s"] for d in draws])),
            "mean_steps": float(np.mean([d["steps"] for d in draws])),
            "public_fit_calls": public,
            "public_vs_reused_max_diff_in_sigma": agreement,
            "total_s": time.perf_counter() - t_begin,
        },
        "draws": draws,
        "versions": {"fwdfit": fwdfit.__version__, "jax": jax.__version__,
                     "optimistix": optx.__version__, "python": platform.python_version()},
        "machine": {"cpus": __import__("os").cpu_count(), "platform": platform.platform()},
    }
    (RESULTS / "fit_calibration.json").write_text(json.dumps(output, indent=1) + "\n")
    print(f"\n{n} draws; coverage of the truth within 1 sigma (expect 0.683 +- "
          f"{math.sqrt(0.683 * 0.317 / n):.3f}), 2 sigma (0.954), pull mean / std, scatter / error:")
    for name, s in summary.items():
        print(f"  {name:<28} {s['coverage_1sigma']:.3f}  {s['coverage_2sigma']:.3f}  "
              f"{s['mean_pull']:+.2f} / {s['std_pull']:.2f}  {s['scatter_over_error']:.2f}")
    print(f"chi2_reduced mean {output['chi2_reduced_mean']:.4f} (std {output['chi2_reduced_std']:.4f}, "
          f"expected {output['chi2_reduced_expected_std']:.4f}); "
          f"converged {output['converged_fraction']:.2f}; "
          f"T_att truth inside its band in {output['T_att_inside_1sigma_mean']:.3f} of pixels")
    print(f"wrote {RESULTS / 'fit_calibration.json'} ({output['timing']['total_s']:.0f} s)")
    return output


if __name__ == "__main__":
    arguments = [a for a in sys.argv[1:] if a != "--quick"]
    main(3 if "--quick" in sys.argv[1:] else int(arguments[0]) if arguments else 40,
         float(arguments[1]) if len(arguments) > 1 else 900.0, quick="--quick" in sys.argv[1:])

"""Posterior sampling with NUTS: effective samples per second, the oxide's SLD valley,
and the coverage of the 68 % credible intervals.

Cases (each: fit, then ``fwdfit.sample`` from the fit's optimum):

- ``al``: the shipped example ``examples/al_block`` (five profiles, five free values).
  Reported: posterior mean - least-squares value in fit errors, posterior sd / fit
  error (goal: within 0.3 and 20 %), effective samples per second, R-hat, divergences.
- ``oxide``: the five-layer oxide of the independent ray tracer
  (``tests/data/raytrace/oxide5_boa``) plus 0.5 % Gaussian noise (T_err = that noise and
  the tracer's own error in quadrature, as tests/test_fit_starts.py makes it), ten free
  values. Reported: the posterior correlation of the two oxide SLDs against the
  covariance's, and the posterior sd / fit error of every parameter.
- ``coverage``: ``--noise-draws`` (default 20) noise draws of the Al example's truth
  (``fwdfit.simulate`` + 0.5 % noise); the share of draws whose 16-84 % credible interval
  holds the truth (goal 68 ± 10 %), and for comparison the share whose least-squares value ± its
  error does, draw by draw. One ``Fitter``, so the model and gradient compile once.
- ``fit_coverage``: the same noise draws, the least-squares errors alone (no sampling), so that
  many draws (``--noise-draws 200``, a few minutes) show what share the first 20 or 40 give.

    python benchmarks/sampler.py [al] [oxide] [coverage] [fit_coverage] [--draws N] [--warmup W]
        [--chains C] [--accuracy A] [--noise-draws N] [--resume] [--quick]

Writes ``benchmarks/results/sampler.json``; costs on 2 CPU cores are in the file.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
import warnings
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import fwdfit  # noqa: E402

from _results import machine_record, results_dir  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
AL_SCENE = ROOT / "examples" / "al_block" / "scene.toml"
OXIDE = ROOT / "tests" / "data" / "raytrace" / "oxide5_boa"
OXIDE_VARY = ("sample.tilt_deg", "sample.centre_um", "layers.oxide2_left.thickness_um",
              "layers.oxide1_left.thickness_um", "layers.Al.thickness_um", "layers.oxide2_left.sld_e6_per_A2",
              "layers.oxide1_left.sld_e6_per_A2", "layers.oxide2_left.mu_per_m",
              "layers.oxide1_left.mu_per_m", "layers.Al.mu_per_m")
AL_TRUTH = {"sample.tilt_deg": 0.24, "sample.centre_um": 3.0, "layers.Al.thickness_um": 1000.0}
NOISE = 0.005


def _compare(posterior) -> dict:
    fit = posterior.fit
    return {name: {"mean_minus_fit_in_errors": float((m - v) / e), "sd_over_error": float(s / e),
                   "ess": float(ess), "rhat": float(r), "ess_per_s": float(eps)}
            for name, m, s, v, e, ess, r, eps in zip(posterior.names, posterior.mean, posterior.sd, fit.values,
                                                    fit.errors, posterior.ess, posterior.rhat, posterior.ess_per_s)}


def _run(scene, args) -> dict:
    begin = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        posterior = fwdfit.sample(scene, args.draws, chains=args.chains, warmup=args.warmup,
                                  accuracy=args.accuracy)
    print(posterior.table(), flush=True)
    return {"parameters": _compare(posterior), "divergences": posterior.divergences,
            "acceptance_rate": posterior.acceptance_rate, "min_ess_per_s": float(np.min(posterior.ess_per_s)),
            "sampling_time_s": posterior.sampling_time_s, "gradient_compile_time_s": posterior.compile_time_s,
            "fit_wall_time_s": posterior.fit.wall_time_s, "total_time_s": time.perf_counter() - begin,
            "posterior_correlation": posterior.correlation.tolist(),
            "covariance_correlation": posterior.fit.correlation.tolist(), "names": list(posterior.names)}


def oxide_scene(seed: int = 0):
    """The ray-traced oxide with 0.5 % noise added, ten free values (a Scene value)."""
    scene = fwdfit.load_scene(OXIDE / "scene.toml")
    rng = np.random.default_rng(seed)
    profiles = []
    for p in scene.profiles:
        table = np.loadtxt(OXIDE / f"{p.name}.csv", delimiter=",", skiprows=1)
        T = table[:, 1] + rng.normal(0.0, NOISE, len(table))
        profiles.append(dataclasses.replace(p, x_um=table[:, 0], T=T, T_err=np.hypot(NOISE, table[:, 2])))
    return dataclasses.replace(scene, profiles=tuple(profiles), fit=fwdfit.FitSpec(OXIDE_VARY, {}))


def coverage(args, kept: dict, save, sample: bool = True) -> dict:
    """Share of noise draws whose 16-84 % credible interval holds the truth, per parameter
    (``args.noise_draws`` draws; the first ones are the same whatever the count). kept: an
    earlier run's record of the same settings, whose draws are kept (``--resume``); save:
    called with the record after every draw, so that a stopped run can be resumed. sample:
    False for the least-squares errors alone (``fit_coverage``: many draws in minutes)."""
    n_draws = args.noise_draws
    scene = fwdfit.load_scene(AL_SCENE)
    truth_scene = dataclasses.replace(scene, sample=dataclasses.replace(
        scene.sample, tilt_deg=AL_TRUTH["sample.tilt_deg"], centre_um=AL_TRUTH["sample.centre_um"],
        layers=(dataclasses.replace(scene.sample.layers[0], thickness_um=AL_TRUTH["layers.Al.thickness_um"]),)))
    truth_T = [p.T for p in fwdfit.simulate(truth_scene, args.accuracy)]
    fitter = fwdfit.Fitter(scene, accuracy=args.accuracy)
    hits, fit_hits = list(kept.get("hits", []))[:n_draws], list(kept.get("fit_hits", []))[:n_draws]
    rng, begin = np.random.default_rng(1), time.perf_counter()
    share = lambda h: {n: float(np.mean([d[n] for d in h])) for n in AL_TRUTH}
    record = kept
    for k in range(n_draws):
        T = [t + rng.normal(0.0, NOISE, t.shape) for t in truth_T]  # drawn for kept draws too
        if k < len(fit_hits):
            continue
        result = fitter(T, [np.full_like(t, NOISE) for t in T])
        if sample:
            posterior = fwdfit.sample(scene, args.draws, chains=args.chains, warmup=args.warmup, seed=k,
                                      fitter=fitter, result=result, T=T, T_err=[np.full_like(t, NOISE) for t in T])
            flat = posterior.draws.reshape(-1, len(posterior.names))
            low, high = np.percentile(flat, [16, 84], axis=0)
            hits.append({n: bool(low[j] <= AL_TRUTH[n] <= high[j]) for j, n in enumerate(posterior.names)
                         if n in AL_TRUTH})
        fit_hits.append({n: bool(abs(v - AL_TRUTH[n]) <= e) for n, v, e in zip(result.names, result.values,
                                                                               result.errors) if n in AL_TRUTH})
        print(k, (hits or fit_hits)[-1], f"{time.perf_counter() - begin:.0f} s", flush=True)
        record = {"draws": len(fit_hits), "fit_errors": share(fit_hits), "fit_hits": fit_hits}
        if sample:
            record |= share(hits) | {"pooled": float(np.mean([v for h in hits for v in h.values()])), "hits": hits}
        save(record)
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cases", nargs="*", default=["al", "oxide"],
                        choices=["al", "oxide", "coverage", "fit_coverage"])
    parser.add_argument("--draws", type=int, default=500)
    parser.add_argument("--warmup", type=int, default=300)
    parser.add_argument("--chains", type=int, default=4)
    parser.add_argument("--accuracy", type=float, default=None)
    parser.add_argument("--noise-draws", type=int, default=20, help="coverage: noise realisations")
    parser.add_argument("--resume", action="store_true",
                        help="coverage: keep the draws of an earlier run with the same settings")
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: the Al example only, 2 chains x 100 draws, accuracy 0.01")
    args = parser.parse_args()
    if args.quick:
        args.cases, args.draws, args.warmup, args.chains, args.accuracy = ["al"], 100, 100, 2, 0.01
    fwdfit.enable_compilation_cache()
    path = results_dir(args.quick) / "sampler.json"
    results = json.loads(path.read_text()) if path.exists() else {}
    for case in args.cases:
        print(f"== {case}", flush=True)
        if case == "al":
            results[case] = _run(fwdfit.load_scene(AL_SCENE), args)
        elif case == "oxide":
            results[case] = _run(oxide_scene(), args)
        else:
            settings = {k: v for k, v in vars(args).items() if k not in ("cases", "noise_draws", "resume")}
            earlier = results.get(case, {})
            kept = earlier if args.resume and earlier.get("settings") == settings else {}

            def save(record, case=case, settings=settings):
                results[case] = record | {"settings": settings}
                results["machine"] = machine_record()
                path.write_text(json.dumps(results, indent=2) + "\n")
            save(coverage(args, kept, save, sample=case == "coverage"))
            continue
        results[case]["settings"] = vars(args) | {"cases": None}
        results["machine"] = machine_record()
        path.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

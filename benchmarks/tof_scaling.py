"""Time-of-flight scaling: forward model and whole fit against the number of wavelength bins.

    python benchmarks/tof_scaling.py [--bins 25 100 400] [--pixels 1000] [--no-fit] [--quick]

A 1 mm NCrystal Al block (Al_sg225.ncmat, 2 mm deep, tilt 0.24 deg) seen in N band
spectra (``lambda_min_A``/``lambda_max_A``) tiling 1.5-6 Å, so several bins straddle
the Bragg edges; every bin is one profile of ``--pixels`` pixels (2.4 µm) at 5 mm.
For each N: the plan (build_model), tracing, XLA compile and one evaluation of the
flat prediction (``ForwardModel.flat``: T and T_att of all bins, float64, mean of
repeats), the traced program's size (jaxpr equations) and the number of profile groups
(one static plan each); then a whole fit of 4 free parameters (thickness, tilt, centre,
density scale; starts +20 µm, -0.04 deg, -3 µm, 1.0) to the model's own prediction at
the truth (density scale 0.97) plus 1 % noise: compile and solve times, evaluations and
the errors of the fitted values, in a fresh process (as a user's fit runs: in the
process that measured the forward model the same fit took ~25 % longer). Writes
benchmarks/results/tof_scaling.json (quick: results/quick/).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time

from _results import machine_record, results_dir

LAMBDA_RANGE_A = (1.5, 6.0)
PIXEL_UM = 2.4

def scene_of(n_bins: int, pixels: int):
    """The NCrystal Al block at 5 mm: one band spectrum and one profile per bin."""
    import fwdfit

    lo, hi = LAMBDA_RANGE_A
    edges = [lo + (hi - lo) * i / n_bins for i in range(n_bins + 1)]
    half = 0.5 * pixels * PIXEL_UM
    names = [f"b{i:03d}" for i in range(n_bins)]
    layer = fwdfit.Layer.from_material("Al", 1000.0, fwdfit.constants_from_ncrystal("Al_sg225.ncmat"))
    return fwdfit.Scene(
        sample=fwdfit.Sample(depth_mm=2.0, tilt_deg=0.24, centre_um=0.0, layers=(layer,)),
        instruments={"": fwdfit.Instrument("circular", 20.0, 10.0, PIXEL_UM)},
        spectra={name: fwdfit.BandSpectrum(a, b) for name, a, b in zip(names, edges[:-1], edges[1:])},
        profiles=tuple(fwdfit.Profile(name, 5.0, name, "", fwdfit.pixel_grid(-half, half, PIXEL_UM))
                       for name in names))


def measure(n_bins: int, pixels: int, repeats: int) -> dict:
    import equinox as eqx
    import jax

    import fwdfit

    scene = scene_of(n_bins, pixels)
    start = time.perf_counter()
    model = fwdfit.build_model(scene)
    plan_s = time.perf_counter() - start
    params = fwdfit.initial_params(scene)
    evaluate = eqx.filter_jit(lambda m, p: m.flat(p))
    start = time.perf_counter()
    lowered = evaluate.lower(model, params)
    trace_s = time.perf_counter() - start
    start = time.perf_counter()
    compiled = lowered.compile()
    compile_s = time.perf_counter() - start
    jax.block_until_ready(compiled(model, params))
    start = time.perf_counter()
    for _ in range(repeats):
        jax.block_until_ready(compiled(model, params))
    eval_s = (time.perf_counter() - start) / repeats
    equations = len(jax.make_jaxpr(lambda p: model.flat(p))(params).jaxpr.eqns)
    return {"bins": n_bins, "pixels": pixels, "groups": len(model.groups), "jaxpr_equations": equations,
            "wavelength_nodes": sorted({int(g.wavelength_A.shape[1]) for g in model.groups}),
            "plan_s": round(plan_s, 3), "trace_s": round(trace_s, 3), "compile_s": round(compile_s, 3),
            "eval_s": round(eval_s, 4), "eval_ms_per_bin": round(1e3 * eval_s / n_bins, 3)}


TRUTH = {"layers.Al.thickness_um": 1000.0, "sample.tilt_deg": 0.24, "sample.centre_um": 0.0,
         "layers.Al.density_scale": 0.97}
START = {"layers.Al.thickness_um": 1020.0, "sample.tilt_deg": 0.20, "sample.centre_um": -3.0,
         "layers.Al.density_scale": 1.0}


def fit_case(n_bins: int, pixels: int) -> dict:
    """The whole fit of 4 free parameters to the model's prediction at the truth plus 1 % noise."""
    import numpy as np

    import fwdfit

    truth = scene_of(n_bins, pixels)
    layer = dataclasses.replace(truth.sample.layers[0], density_scale=TRUTH["layers.Al.density_scale"])
    truth = dataclasses.replace(truth, sample=dataclasses.replace(truth.sample, layers=(layer,)))
    T, _ = fwdfit.build_model(truth)(fwdfit.initial_params(truth))
    rng = np.random.default_rng(1)
    profiles = tuple(dataclasses.replace(p, T=np.asarray(t) + 0.01 * rng.standard_normal(len(p.x_um)),
                                         T_err=np.full(len(p.x_um), 0.01)) for p, t in zip(truth.profiles, T))
    layer = dataclasses.replace(layer, thickness_um=START["layers.Al.thickness_um"],
                                density_scale=START["layers.Al.density_scale"])
    sample = dataclasses.replace(truth.sample, layers=(layer,), tilt_deg=START["sample.tilt_deg"],
                                 centre_um=START["sample.centre_um"])
    scene = dataclasses.replace(truth, sample=sample, profiles=profiles, fit=fwdfit.FitSpec(tuple(TRUTH)))
    start = time.perf_counter()
    fitter = fwdfit.Fitter(scene)
    setup_s = time.perf_counter() - start
    start = time.perf_counter()
    result = fitter()
    solve_s = time.perf_counter() - start
    fitted = dict(zip(result.names, result.values))
    return {"fit_setup_s": round(setup_s, 2), "fit_compile_s": round(result.compile_time_s, 2),
            "fit_solve_s": round(solve_s, 2), "fit_total_s": round(setup_s + solve_s, 2),
            "fit_evaluations": int(result.n_evaluations), "fit_chi2_reduced": round(result.chi2_reduced, 4),
            "fit_converged": bool(result.converged),
            "fit_errors": {k: float(fitted[k] - v) for k, v in TRUTH.items()}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bins", type=int, nargs="+", default=[25, 100, 400])
    parser.add_argument("--pixels", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-fit", action="store_true", help="the forward model only")
    parser.add_argument("--quick", action="store_true", help="25 bins only")
    parser.add_argument("--fit-only", type=int, metavar="BINS", help=argparse.SUPPRESS)  # the fresh fit process
    args = parser.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    if args.fit_only:
        print(json.dumps(fit_case(args.fit_only, args.pixels)))
        return
    rows = []
    for n in [25] if args.quick else args.bins:
        rows.append(measure(n, args.pixels, args.repeats))
        if not args.no_fit:
            fit = subprocess.run([sys.executable, __file__, "--fit-only", str(n), "--pixels", str(args.pixels)],
                                 capture_output=True, text=True, check=True)
            rows[-1].update(json.loads(fit.stdout.splitlines()[-1]))
        rows[-1]["load_1min"] = round(os.getloadavg()[0], 2)  # others' work on the shared cores inflates times
        print(json.dumps(rows[-1]), flush=True)
    out = results_dir(args.quick) / "tof_scaling.json"
    out.write_text(json.dumps({"rows": rows, "machine": machine_record()}, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

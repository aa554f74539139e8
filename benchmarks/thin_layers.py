"""Thin-layer convergence: RMS error of the model against the exact tracer vs layer thickness.

An oxide skin (SLD 4.5e-6 Å^-2, mu 100 /m + 0.3 /m/Å) of thickness t on both sides of 1 mm
of Al (the Al faces fixed at +-500 µm), BOA white beam (square 40 mm at 7.5 m), profiles over
the left edge at 1.1 and 10 mm, tilts 0 and 0.24°, t = 0, 0.5, 1, 2, 5, 10, 20 µm. One
compiled model (the skin thickness free, so the coupled thin-layer kernels serve every t);
the tracer (``fwdfit.reference``) with N rays per profile. Also: one evaluation's time and
the compile time, against the bare Al block on the same pixels (no thin layer). ``--fresnel``:
the same with Fresnel partial reflection in the model and the tracer.

    python benchmarks/thin_layers.py [--quick] [--fresnel]
        -> benchmarks/results/thin_layers[_fresnel].{json,md}
"""

from __future__ import annotations

import argparse
import json
import os
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import fwdfit  # noqa: E402
from fwdfit.reference import ReferenceLayer, trace_reference  # noqa: E402
from fwdfit.scene import read_columns  # noqa: E402

from benchmarks._results import ROOT, machine_record, results_dir  # noqa: E402

THICKNESS_UM = (0.0, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0)
TILTS_DEG = (0.0, 0.24)
DISTANCES_MM = (1.1, 10.0)
SKIN = dict(sld_e6_per_A2=4.5, mu_per_m=100.0, mu_per_m_per_A=0.3)
AL = dict(sld_e6_per_A2=2.078, mu_per_m=1.39, mu_per_m_per_A=0.1)
SPECTRUM = ROOT / "tests" / "data" / "raytrace_thin" / "spectrum_boa.csv"


def scene(thickness_um: float, skin: bool = True, fresnel: bool = False) -> fwdfit.Scene:
    table = read_columns(SPECTRUM, ("lambda_A", "weight"))
    layers = (fwdfit.Layer("Al", 1000.0, **AL),)
    if skin:
        layers = (fwdfit.Layer("skin_l", thickness_um, **SKIN),) + layers + (fwdfit.Layer("skin_r", thickness_um, **SKIN),)
    grid = {1.1: fwdfit.pixel_grid(-600.0, -400.0, 2.4), 10.0: fwdfit.pixel_grid(-720.0, -280.0, 2.4)}
    return fwdfit.Scene(
        sample=fwdfit.Sample(depth_mm=2.0, tilt_deg=0.0, centre_um=0.0, layers=layers),
        instruments={"boa": fwdfit.Instrument("square", 40.0, 7.5, 2.4, fresnel=fresnel)},
        spectra={"white": fwdfit.TabulatedSpectrum(table["lambda_A"], table["weight"], SPECTRUM)},
        profiles=tuple(fwdfit.Profile(f"d{d:04.1f}mm", d, "white", "boa", grid[d]) for d in DISTANCES_MM),
        fit=fwdfit.FitSpec(("layers.skin_l.thickness_um", "layers.skin_r.thickness_um") if skin else ()))


def timed(function, *args, repeat=5):
    start = time.perf_counter()
    jax.block_until_ready(function(*args))
    first = time.perf_counter() - start
    start = time.perf_counter()
    for _ in range(repeat):
        jax.block_until_ready(function(*args))
    return first, (time.perf_counter() - start) / repeat


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer rays, thicknesses 0, 2, 20 µm")
    parser.add_argument("--fresnel", action="store_true", help="Fresnel partial reflection on")
    args = parser.parse_args()
    rays = {1.1: 1_000_000, 10.0: 2_000_000} if args.quick else {1.1: 8_000_000, 10.0: 12_000_000}
    thicknesses = (0.0, 2.0, 20.0) if args.quick else THICKNESS_UM
    base = scene(2.0, fresnel=args.fresnel)
    model = fwdfit.build_model(base, free=base.fit.vary, tilt_range_deg=(0.0, 0.24))
    bare = scene(0.0, skin=False, fresnel=args.fresnel)
    bare_model = fwdfit.build_model(bare, tilt_range_deg=(0.0, 0.24))
    params, bare_params = fwdfit.initial_params(base), fwdfit.initial_params(bare)
    compile_s, eval_s = timed(eqx.filter_jit(model), params)
    bare_compile_s, bare_eval_s = timed(eqx.filter_jit(bare_model), bare_params)
    run = eqx.filter_jit(model)
    table = read_columns(SPECTRUM, ("lambda_A", "weight"))
    rows = []
    for tilt in TILTS_DEG:
        for t in thicknesses:
            p = eqx.tree_at(lambda q: (q.thickness_um, q.tilt_deg), params,
                            (jnp.asarray([t, 1000.0, t]), jnp.asarray(tilt)))
            T, T_att = run(p)
            layers = [ReferenceLayer(t, **SKIN), ReferenceLayer(1000.0, **AL), ReferenceLayer(t, **SKIN)]
            for i, profile in enumerate(base.profiles):
                edges = np.append(profile.x_um - 1.2, profile.x_um[-1] + 1.2)
                start = time.perf_counter()
                ref = trace_reference(layers, depth_mm=2.0, tilt_deg=tilt, centre_um=0.0, aperture="square",
                                      aperture_mm=40.0, aperture_distance_m=7.5, distance_mm=profile.distance_mm,
                                      spectrum_lambda_A=table["lambda_A"], spectrum_weight=table["weight"],
                                      pixel_edges_um=edges, n_rays=rays[profile.distance_mm], seed=7 + i,
                                      fresnel=args.fresnel)
                rms = lambda a: float(np.sqrt(np.nanmean(np.square(a))))
                rows.append({"thickness_um": t, "tilt_deg": tilt, "distance_mm": profile.distance_mm,
                             "rms_T": rms(np.asarray(T[i]) - ref.T), "rms_T_att": rms(np.asarray(T_att[i]) - ref.T_att),
                             "tracer_noise_rms": rms(ref.T_err), "n_rays": rays[profile.distance_mm],
                             "trace_s": round(time.perf_counter() - start, 1)})
                print(rows[-1], flush=True)
    result = {"machine": machine_record(), "load_average": os.getloadavg(), "fresnel": args.fresnel,
              "evaluation_s": {"skin_coupled": eval_s, "bare_al": bare_eval_s},
              "compile_s": {"skin_coupled": compile_s, "bare_al": bare_compile_s}, "rows": rows}
    folder, name = results_dir(args.quick), "thin_layers_fresnel" if args.fresnel else "thin_layers"
    (folder / f"{name}.json").write_text(json.dumps(result, indent=1) + "\n")
    lines = ["| t (µm) | tilt (°) | distance (mm) | RMS T - T_ref | RMS T_att - T_att,ref | tracer noise RMS |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {r['thickness_um']:g} | {r['tilt_deg']:g} | {r['distance_mm']:g} | {r['rms_T']:.4f} | "
              f"{r['rms_T_att']:.4f} | {r['tracer_noise_rms']:.4f} |" for r in rows]
    lines += ["", f"One evaluation (2 profiles, float64): coupled skins {eval_s * 1e3:.0f} ms, bare Al "
              f"{bare_eval_s * 1e3:.0f} ms; compile + first call {compile_s:.0f} s vs {bare_compile_s:.0f} s "
              f"(load average {os.getloadavg()[0]:.1f})."]
    (folder / f"{name}.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()

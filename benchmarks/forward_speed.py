"""Forward-model speed on the 10-distance BOA Al scene (compile and evaluation times).

    python benchmarks/forward_speed.py [--pixels 670] [--quick]

Uses tests/data/mcstas/scene_boa_tilt0.24.toml (10 distances 1.1-34.4 mm, white
beam, 0.24 deg tilt) with each profile cut to ``--pixels`` pixels around the
centre; times one evaluation of all profiles (T and T_att) after compilation, in
float64 and float32, one forward-mode Jacobian with respect to five parameters
(what the errors need) and five forward differences (what a solver step needs).
Then, in float64, the evaluation time with Fresnel partial reflection off and on
(``fresnel = true``) for this scene, the shipped example (examples/al_block) and the
five-layer oxide (tests/data/raytrace/oxide5_boa), whole profiles
(``--fresnel-only`` runs just that part). Writes benchmarks/results/forward_speed.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

from _results import results_dir

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "tests/data/mcstas/scene_boa_tilt0.24.toml"
FRESNEL_SCENES = {"boa_al_10_distances": SCENE, "example_al_block": ROOT / "examples/al_block/scene.toml",
                  "oxide5_boa": ROOT / "tests/data/raytrace/oxide5_boa/scene.toml"}


def _timed_evaluation(model, params, repeats: int) -> tuple[float, float]:
    """(compile s, evaluation ms) of ``model(params)``."""
    import equinox as eqx
    import jax

    evaluate = eqx.filter_jit(lambda m, p: m(p))
    start = time.perf_counter()
    compiled = evaluate.lower(model, params).compile()
    compile_s = time.perf_counter() - start
    jax.block_until_ready(compiled(model, params))
    start = time.perf_counter()
    for _ in range(repeats):
        jax.block_until_ready(compiled(model, params))
    return compile_s, (time.perf_counter() - start) / repeats * 1e3


def measure_fresnel(repeats: int = 10) -> list[dict]:
    """Float64 compile and evaluation times of each of ``FRESNEL_SCENES`` with Fresnel off and on."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import fwdfit

    rows = []
    for name, path in FRESNEL_SCENES.items():
        scene = fwdfit.load_scene(path)
        row = {"scene": name, "profiles": len(scene.profiles)}
        for fresnel in (False, True):
            instruments = {k: dataclasses.replace(v, fresnel=fresnel) for k, v in scene.instruments.items()}
            variant = dataclasses.replace(scene, instruments=instruments)
            compile_s, eval_ms = _timed_evaluation(fwdfit.build_model(variant), fwdfit.initial_params(variant),
                                                   repeats)
            key = "fresnel" if fresnel else "sharp"
            row[f"{key}_compile_s"], row[f"{key}_eval_ms"] = round(compile_s, 2), round(eval_ms, 2)
        row["eval_ratio"] = round(row["fresnel_eval_ms"] / row["sharp_eval_ms"], 2)
        rows.append(row)
    return rows


def measure(pixels: int, x64: bool, repeats: int = 20) -> dict:
    import jax

    jax.config.update("jax_enable_x64", x64)
    import equinox as eqx
    import jax.numpy as jnp
    import numpy as np

    import fwdfit

    scene = fwdfit.load_scene(SCENE)
    keep = lambda x: x[np.argsort(np.abs(x))[:pixels]].copy()
    profiles = tuple(dataclasses.replace(p, x_um=np.sort(keep(p.x_um))) for p in scene.profiles)
    scene = dataclasses.replace(scene, profiles=profiles)
    model = fwdfit.build_model(scene)
    params = fwdfit.initial_params(scene)
    compile_s, eval_ms = _timed_evaluation(model, params, repeats)

    def outputs(m, v):
        p = eqx.tree_at(lambda q: (q.tilt_deg, q.centre_um), params, (v[0], v[1]))
        p = eqx.tree_at(lambda q: (q.thickness_um, q.sld_e6_per_A2, q.mu_per_m), p,
                        (v[2:3], v[3:4], v[4:5]))
        return jnp.concatenate(m(p)[0])

    jacobian = eqx.filter_jit(lambda m, v: jax.jacfwd(lambda u: outputs(m, u))(v))
    v0 = jnp.array([0.24, 0.0, 1000.0, 2.0787, 9.059], dtype=params.tilt_deg.dtype)
    start = time.perf_counter()
    compiled_j = jacobian.lower(model, v0).compile()
    jac_compile_s = time.perf_counter() - start
    jax.block_until_ready(compiled_j(model, v0))
    start = time.perf_counter()
    for _ in range(repeats // 4):
        jax.block_until_ready(compiled_j(model, v0))
    jac_ms = (time.perf_counter() - start) / (repeats // 4) * 1e3

    # What a fit step costs: forward differences, one evaluation per parameter (fwdfit's solver).
    differences = eqx.filter_jit(lambda m, v: jax.lax.map(
        lambda e: outputs(m, v + 1e-6 * e), jnp.eye(v.shape[0], dtype=v.dtype)))
    compiled_d = differences.lower(model, v0).compile()
    jax.block_until_ready(compiled_d(model, v0))
    start = time.perf_counter()
    for _ in range(repeats // 4):
        jax.block_until_ready(compiled_d(model, v0))
    differences_ms = (time.perf_counter() - start) / (repeats // 4) * 1e3
    return {"pixels_per_profile": pixels, "profiles": len(profiles), "float64": x64,
            "compile_s": round(compile_s, 2), "eval_ms": round(eval_ms, 2),
            "jacobian_5_params_compile_s": round(jac_compile_s, 2), "jacobian_5_params_ms": round(jac_ms, 1),
            "forward_differences_5_params_ms": round(differences_ms, 1)}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--pixels", type=int, default=670)
    parser.add_argument("--quick", action="store_true", help="200 pixels per profile (CI smoke run)")
    parser.add_argument("--fresnel-only", action="store_true", help="only the Fresnel off / on timings")
    parser.add_argument("--child", choices=["64", "32", "fresnel"])
    args = parser.parse_args()
    if args.quick:
        args.pixels = 200
    if args.child:
        result = measure_fresnel() if args.child == "fresnel" else measure(args.pixels, args.child == "64")
        print(json.dumps(result))
        return
    out_path = results_dir(args.quick) / "forward_speed.json"
    rows = []
    for precision in () if args.fresnel_only else ("64", "32"):  # fresh processes: x64 is a global switch
        out = subprocess.run([sys.executable, __file__, "--pixels", str(args.pixels), "--child", precision],
                             capture_output=True, text=True, check=True, env={**os.environ})
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
        print(rows[-1])
    out = subprocess.run([sys.executable, __file__, "--child", "fresnel"], capture_output=True, text=True,
                         check=True, env={**os.environ})
    fresnel_rows = json.loads(out.stdout.strip().splitlines()[-1])
    for row in fresnel_rows:
        print(row)
    if args.fresnel_only and out_path.exists():  # keep the other measurements
        rows = json.loads(out_path.read_text())["results"]
    import jax

    record = {"machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                          "device": str(jax.devices()[0]), "jax": jax.__version__},
              "scene": str(SCENE.relative_to(ROOT)), "results": rows, "fresnel": fresnel_rows}
    out_path.write_text(json.dumps(record, indent=2) + "\n")
    print(f"wrote {out_path}")


if __name__ == "__main__":
    main()

"""Forward-model speed on the 10-distance BOA Al scene (compile and evaluation times).

    python benchmarks/forward_speed.py [--pixels 670] [--quick]

Uses tests/data/mcstas/scene_boa_tilt0.24.toml (10 distances 1.1-34.4 mm, white
beam, 0.24 deg tilt) with each profile cut to ``--pixels`` pixels around the
centre; times one evaluation of all profiles (T and T_att) after compilation, in
float64 and float32, one forward-mode Jacobian with respect to five parameters
(what the errors need) and five forward differences (what a solver step needs).
Writes benchmarks/results/forward_speed.json.
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
    evaluate = eqx.filter_jit(lambda m, p: m(p))
    start = time.perf_counter()
    compiled = evaluate.lower(model, params).compile()
    compile_s = time.perf_counter() - start
    jax.block_until_ready(compiled(model, params))
    start = time.perf_counter()
    for _ in range(repeats):
        jax.block_until_ready(compiled(model, params))
    eval_ms = (time.perf_counter() - start) / repeats * 1e3

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
    parser.add_argument("--child", choices=["64", "32"])
    args = parser.parse_args()
    if args.quick:
        args.pixels = 200
    if args.child:
        print(json.dumps(measure(args.pixels, args.child == "64")))
        return
    rows = []
    for precision in ("64", "32"):  # fresh processes: x64 is a global switch
        out = subprocess.run([sys.executable, __file__, "--pixels", str(args.pixels), "--child", precision],
                             capture_output=True, text=True, check=True, env={**os.environ})
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
        print(rows[-1])
    import jax

    record = {"machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                          "device": str(jax.devices()[0]), "jax": jax.__version__},
              "scene": str(SCENE.relative_to(ROOT)), "results": rows}
    out_path = results_dir(args.quick) / "forward_speed.json"
    out_path.write_text(json.dumps(record, indent=2) + "\n")
    print(f"wrote {out_path}")


if __name__ == "__main__":
    main()

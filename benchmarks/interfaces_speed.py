"""Cost of the interface terms: the five-layer oxide with Fresnel reflection, rough faces and
graded layers on, against its sharp model.

    python benchmarks/interfaces_speed.py [--repeats 10] [--variants sharp,fresnel,...]

Scene: tests/data/raytrace/oxide5_boa (five layers, six faces, BOA white beam, its profiles at
1.1, 12.2 and 34.4 mm). Variants: ``sharp`` (as stored), ``fresnel`` (``fresnel = true``), ``rough0.5`` and
``rough2`` (every face 0.5 or 2 mrad), ``graded`` (the inner oxides graded: SLD and mu x 0.8
to x 1.2 across), ``all0.5`` and ``all2`` (Fresnel, every face rough, graded). Times one
float64 evaluation of all profiles (T and T_att) after compilation, the compile time, and the
number of operations in the compiled program's HLO text. Variants the checkout does not know
(an older fwdfit) are skipped, so that the same command measures a baseline checkout; issue 16's
target compares against the sharp evaluation of the checkout it was filed on (dbf0b10):

    git worktree add /tmp/pre16 dbf0b10
    PYTHONPATH=/tmp/pre16/src python benchmarks/interfaces_speed.py --variants sharp \
        --out benchmarks/results/interfaces_speed_dbf0b10.json
    python benchmarks/interfaces_speed.py --baseline benchmarks/results/interfaces_speed_dbf0b10.json

``--baseline`` adds each variant's cost against that file's sharp evaluation (``cost_vs_baseline``).
Writes benchmarks/results/interfaces_speed.json (or ``--out``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

from _results import machine_record, results_dir

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "tests/data/raytrace/oxide5_boa/scene.toml"
VARIANTS = ("sharp", "fresnel", "rough0.5", "rough2", "graded", "all0.5", "all2")


def variant(scene, name: str):
    """The oxide scene with the terms of ``name`` on."""
    fresnel = name == "fresnel" or name.startswith("all")
    rough = float(name.removeprefix("rough").removeprefix("all")) if name[-1].isdigit() else 0.0
    graded = name == "graded" or name.startswith("all")
    scene = dataclasses.replace(scene, instruments={k: dataclasses.replace(v, fresnel=fresnel)
                                                    for k, v in scene.instruments.items()})
    layers = []
    for layer in scene.sample.layers:
        changes = {"roughness_mrad": rough} if rough else {}
        if graded and layer.name.startswith("oxide1"):
            changes |= {"sld_e6_per_A2": 0.8 * layer.sld_e6_per_A2, "mu_per_m": 0.8 * layer.mu_per_m,
                        "sld_end_e6_per_A2": 1.2 * layer.sld_e6_per_A2, "mu_end_per_m": 1.2 * layer.mu_per_m,
                        "same_as": None}
        layers.append(dataclasses.replace(layer, **changes))
    sample = dataclasses.replace(scene.sample, layers=tuple(layers),
                                 **({"left_roughness_mrad": rough} if rough else {}))
    return dataclasses.replace(scene, sample=sample)


def measure(name: str, repeats: int) -> dict:
    import equinox as eqx
    import jax

    import fwdfit

    try:
        scene = variant(fwdfit.load_scene(SCENE), name)
    except TypeError:  # a checkout without the variant's keys
        return {"variant": name, "skipped": "unknown keys in this checkout"}
    model, params = fwdfit.build_model(scene), fwdfit.initial_params(scene)
    evaluate = eqx.filter_jit(lambda m, p: m(p))
    start = time.perf_counter()
    lowered = evaluate.lower(model, params)
    compiled = lowered.compile()
    compile_s = time.perf_counter() - start
    jax.block_until_ready(compiled(model, params))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(compiled(model, params))
        times.append(time.perf_counter() - start)
    hlo = lowered.as_text()
    return {"variant": name, "evaluation_ms": 1e3 * min(times), "evaluation_median_ms": 1e3 * sorted(times)[len(times) // 2],
            "compile_s": compile_s, "hlo_lines": hlo.count("\n")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--baseline", type=Path, default=None,
                        help="results of a baseline checkout (this script's JSON) whose sharp evaluation to compare with")
    args = parser.parse_args()
    baseline = None
    if args.baseline:
        record = json.loads(args.baseline.read_text())
        baseline = {"file": str(args.baseline), "load_average": record["load_average"],
                    "sharp_evaluation_ms": next(r["evaluation_ms"] for r in record["rows"] if r["variant"] == "sharp")}
    import jax

    jax.config.update("jax_enable_x64", True)
    os.environ.setdefault("FWDFIT_CACHE_DIR", "off")
    rows = [measure(name, args.repeats) for name in args.variants.split(",")]
    sharp = next((r for r in rows if r["variant"] == "sharp" and "evaluation_ms" in r), None)
    for row in rows:
        if sharp and "evaluation_ms" in row:
            row["cost_vs_sharp"] = row["evaluation_ms"] / sharp["evaluation_ms"]
        if baseline and "evaluation_ms" in row:
            row["cost_vs_baseline"] = row["evaluation_ms"] / baseline["sharp_evaluation_ms"]
        print(json.dumps(row), flush=True)
    out = args.out or results_dir(False) / "interfaces_speed.json"
    out.write_text(json.dumps({"scene": str(SCENE.relative_to(ROOT)), "load_average": os.getloadavg(),
                               "machine": machine_record(), "baseline": baseline, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()

"""What a program of the shipped example costs to build: per group of profiles, the traced
graph's size (jaxpr equations, nested ones counted), its compile time and evaluation time,
and the same for its exact forward-mode Jacobian (``jax.jacfwd`` in the free values) and
for one Jacobian-vector product (``jax.jvp``, one tangent: a column's own cost).

The baseline of issue 43 (a compact program): a graph whose size does not grow with the
profiles, groups and faces, and a Jacobian that compiles in at most twice the forward
program's time and evaluates in at most 1 + n_free forward evaluations.

    python benchmarks/compile_cost.py [--quick]

Writes benchmarks/results/compile_cost.json. Run on idle cores: compile times scale with load.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402

import fwdfit  # noqa: E402
from fwdfit.inference import assembler, free_parameters, geometry_of  # noqa: E402
from _results import machine_record, write_result  # noqa: E402

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "al_block" / "scene.toml"
REPEATS = 20


def _equations(jaxpr) -> int:
    count = 0
    for equation in jaxpr.eqns:
        count += 1
        for value in equation.params.values():
            inner = getattr(value, "jaxpr", None)
            if inner is not None:
                count += _equations(inner if hasattr(inner, "eqns") else inner.jaxpr)
    return count


def _timed(function, argument) -> tuple[float, float]:
    """(compile s, evaluation ms) of ``jit(function)`` at ``argument``."""
    start = time.perf_counter()
    compiled = jax.jit(function).lower(argument).compile()
    compile_s = time.perf_counter() - start
    jax.block_until_ready(compiled(argument))
    start = time.perf_counter()
    for _ in range(REPEATS):
        jax.block_until_ready(compiled(argument))
    return compile_s, (time.perf_counter() - start) / REPEATS * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="results into results/quick/")
    quick = parser.parse_args().quick
    scene = fwdfit.load_scene(EXAMPLE)
    free = free_parameters(scene)
    model = geometry_of(scene).build_model(scene, None, [p.name for p in free], None)
    assemble = assembler(scene, free)
    values = jax.numpy.asarray([p.value for p in free])
    groups = []
    for group in model.groups:
        part = eqx.tree_at(lambda m: m.groups, model, (group,))

        def forward(v, part=part):
            params, norm, background = assemble(v)
            return part.grouped(params, norm, background)[0][0]

        compile_s, eval_ms = _timed(forward, values)
        jac_compile_s, jac_eval_ms = _timed(jax.jacfwd(forward), values)
        # one tangent: what each column of the Jacobian costs on its own
        along = jax.numpy.ones_like(values)
        jvp_compile_s, jvp_eval_ms = _timed(lambda v, forward=forward: jax.jvp(forward, (v,), (along,)), values)
        groups.append({"profiles": list(group.index), "pixels": int(forward(values).shape[0]),
                       "equations": _equations(jax.make_jaxpr(forward)(values).jaxpr),
                       "jacobian_equations": _equations(jax.make_jaxpr(jax.jacfwd(forward))(values).jaxpr),
                       "compile_s": round(compile_s, 2), "eval_ms": round(eval_ms, 2),
                       "jacobian_compile_s": round(jac_compile_s, 2), "jacobian_eval_ms": round(jac_eval_ms, 2),
                       "jvp_compile_s": round(jvp_compile_s, 2), "jvp_eval_ms": round(jvp_eval_ms, 2)})
        print(groups[-1], flush=True)
    total = {key: round(sum(g[key] for g in groups), 2) for key in
             ("equations", "compile_s", "eval_ms", "jacobian_compile_s", "jacobian_eval_ms", "jvp_compile_s",
              "jvp_eval_ms")}
    total["jacobian_compile_ratio"] = round(total["jacobian_compile_s"] / total["compile_s"], 2)
    total["jacobian_eval_in_forward_evaluations"] = round(total["jacobian_eval_ms"] / total["eval_ms"], 1)
    total["jvp_eval_in_forward_evaluations"] = round(total["jvp_eval_ms"] / total["eval_ms"], 1)
    record = {"scene": "examples/al_block", "n_free": len(free), "groups": groups, "total": total,
              "machine": machine_record()}
    write_result("compile_cost", record, quick)
    print(total)


if __name__ == "__main__":
    main()

"""What the fit would cost with optimistix's Levenberg-Marquardt on the exact Jacobian, against
the host solver fwdfit uses (issue 43, item 2: the solver chosen by measurement).

The shipped example's whole model (every group of profiles) as one JAX residual function of
the unconstrained coordinates, ``optimistix.least_squares`` with ``LevenbergMarquardt``
(QR by lineax, the Jacobian by forward-mode differentiation), jit-compiled as one program,
from each of the starting points the host solver's last local solve was given (the global
scan's best points); beside it ``fwdfit.Fitter`` (host Levenberg-Marquardt, difference
Jacobians through the per-group programs) on the same scene, its local solve timed alone. Each in a fresh
process, so that neither finds the other's programs; the optimistix program's compile is
stopped after ``--limit`` seconds and then reported as longer than that.

    python benchmarks/optimistix_solver.py [--limit S] [--quick]

Writes ``benchmarks/results/optimistix_solver.json`` (``--quick``: a 120 s limit, into
results/quick/). Run on idle cores: compile times scale with load.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
EXAMPLE = HERE.parent / "examples" / "al_block" / "scene.toml"


def _optimistix_child(starts: list[list[float]]) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import equinox as eqx
    import jax.numpy as jnp
    import lineax
    import numpy as np
    import optimistix

    import fwdfit
    from fwdfit.inference import assembler, free_parameters, geometry_of

    scene = fwdfit.load_scene(EXAMPLE)
    free = free_parameters(scene)
    model = geometry_of(scene).build_model(scene, None, [p.name for p in free], None)
    assemble = assembler(scene, free)
    T = jnp.asarray(np.concatenate([p.T for p in scene.profiles]))
    sigma = jnp.asarray(np.concatenate([p.T_err for p in scene.profiles]))

    def residuals(u, arguments):
        model, assemble, T, sigma = arguments
        values = jnp.stack([p.from_unit(u[j], xp=jnp) for j, p in enumerate(free)])
        params, norm, background = assemble(values)
        return (model.flat(params, norm, background)[0] - T) / sigma

    @eqx.filter_jit
    def solve(u0, arguments):
        solver = optimistix.LevenbergMarquardt(rtol=1e-6, atol=1e-6, linear_solver=lineax.QR())
        solution = optimistix.least_squares(residuals, solver, u0, args=arguments, max_steps=200, throw=False)
        r = residuals(solution.value, arguments)
        return solution.value, jnp.sum(r * r), solution.stats["num_steps"]

    arguments = (model, assemble, T, sigma)
    starts = jnp.asarray(starts)
    start = time.perf_counter()
    compiled = solve.lower(starts[0], arguments).compile()
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    out = [jax.block_until_ready(compiled(u0, arguments)) for u0 in starts]
    return {"compile_s": round(compile_s, 1), "solve_s": round(time.perf_counter() - start, 2),
            "chi2_per_start": [float(chi2) for _, chi2, _ in out], "steps_per_start": [int(s) for _, _, s in out]}


def _host_child() -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import fwdfit

    from fwdfit.inference import levenberg_marquardt

    calls = []

    def recorded(residuals, u0, typical, **options):  # the host solver, its starts and its cost noted
        rows = [0]

        def counted(u):
            rows[0] += len(u)
            return residuals(u)

        begin = time.perf_counter()
        solution = levenberg_marquardt(counted, u0, typical, **options)
        calls.append({"starts": u0.tolist(), "chi2_per_start": solution.chi2.tolist(),
                      "model_evaluations": rows[0], "solve_s": time.perf_counter() - begin})
        return solution

    start = time.perf_counter()
    fitter = fwdfit.Fitter(str(EXAMPLE), solver=recorded)
    build_s = time.perf_counter() - start
    result = fitter()
    local = calls[-1]  # the last local solve: every parameter free, from the scan's best points
    return {"compile_s": round(fitter.compile_time_s, 1), "build_s": round(build_s, 1),
            "fit_s": round(result.wall_time_s, 2), "chi2": float(result.chi2), "steps": int(result.n_steps),
            "fit_model_evaluations": int(result.n_evaluations), "local_solve_s": round(local["solve_s"], 2),
            "local_model_evaluations": local["model_evaluations"], "chi2_per_start": local["chi2_per_start"],
            "starts": local["starts"]}


def _run(which: str, limit: float, starts=None) -> dict:
    start = time.perf_counter()
    try:
        run = subprocess.run([sys.executable, __file__, "--child", which], capture_output=True, text=True,
                             timeout=limit, input=json.dumps(starts))
    except subprocess.TimeoutExpired:
        return {"compile_s": f"> {limit:.0f}", "finished": False}
    if run.returncode != 0:
        raise RuntimeError(run.stderr[-2000:])
    return {**json.loads(run.stdout.strip().splitlines()[-1]), "process_s": round(time.perf_counter() - start, 1),
            "finished": True}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--limit", type=float, default=600.0, help="seconds the optimistix process may run")
    parser.add_argument("--quick", action="store_true", help="a 120 s limit, results into results/quick/")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(_optimistix_child(json.loads(sys.stdin.read())) if args.child == "optimistix"
                         else _host_child()))
        return
    from _results import machine_record, write_result

    limit = 120.0 if args.quick else args.limit
    host = _run("host", limit)
    record = {"scene": "examples/al_block", "host_levenberg_marquardt": host,
              "optimistix_levenberg_marquardt": _run("optimistix", limit, host.pop("starts")), "limit_s": limit,
              "machine": machine_record()}
    write_result("optimistix_solver", record, args.quick)
    print(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()

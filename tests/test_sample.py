"""Posterior sampling (NUTS, ``fwdfit fit --sample N``) on a small synthetic Al block.

One ICON line profile of an Al block (the model at a known truth plus 1 % Gaussian
noise, T_err = the noise), three free values. With 3000 pixels at 1 % noise the
posterior is Gaussian to a good approximation, so the least-squares fit's optimum and
covariance are an independent reference: the posterior means must lie within 0.3
standard errors of the fitted values and the posterior standard deviations within 20 %
of the covariance errors. Also: the files are written, and bad input is a one-line error.
"""

from __future__ import annotations

import json
import math

import jax.numpy as jnp
import numpy as np
import pytest

import fwdfit
from fwdfit.inference import FreeParameter
from fwdfit.inference import blackjax_module, diagnostics
from fwdfit.cli import main
from helpers import small_scene

pytest.importorskip("blackjax")

NOISE = 0.01
TRUTH = {"sample.centre_um": 2.0, "layers.Al.thickness_um": 1000.0, "layers.Al.sld_e6_per_A2": 2.078}


VARY = ("sample.centre_um", "layers.Al.thickness_um", "layers.Al.sld_e6_per_A2")
BOUNDS = {"layers.Al.thickness_um": (900.0, 1100.0)}
DRAWS = 150  # per chain, 2 chains


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sample")
    simulated = fwdfit.simulate(small_scene(TRUTH))[0]
    T = simulated.T + np.random.default_rng(3).normal(0.0, NOISE, simulated.T.shape)
    np.savetxt(folder / "line.csv", np.column_stack([simulated.x_um, T, np.full_like(T, NOISE)]),
               delimiter=",", header="x_um,T,T_err", comments="", fmt="%.9g")
    return fwdfit.save_scene(small_scene(TRUTH, file=folder / "line.csv", vary=VARY, bounds=BOUNDS),
                             folder / "scene.toml")


@pytest.fixture(scope="module")
def sampled(scene_path, tmp_path_factory):
    out = tmp_path_factory.mktemp("out") / "fit"
    status = main(["fit", str(scene_path), "--out", str(out), "--quiet", "--sample", str(DRAWS),
                   "--chains", "2", "--warmup", "100"])
    return status, out


@pytest.mark.parametrize("low, high", [(900.0, 1100.0), (0.0, math.inf), (-math.inf, 5.0), (-math.inf, math.inf)])
def test_log_jacobian_of_the_bound_transform(low, high):
    """log(d value / d u) against central differences of from_unit, also deep in a bound's tail."""
    p = FreeParameter("x", 1.0, low, high, 0.5, ("thickness_um", (0,)))
    u = np.array([-30.0, -3.0, -0.2, 0.0, 0.7, 4.0, 25.0])
    h = 1e-5
    numeric = (p.from_unit(u + h) - p.from_unit(u - h)) / (2 * h)
    exact = p.log_value_per_unit(u)
    finite = numeric > 1e-200
    assert np.allclose(exact[finite], np.log(numeric[finite]), atol=1e-6)
    assert np.all(np.isfinite(exact))
    assert np.allclose(np.asarray(p.log_value_per_unit(jnp.asarray(u), jnp)), exact, rtol=1e-12)
    assert np.allclose(np.asarray(p.from_unit(jnp.asarray(u), jnp)), p.from_unit(u), rtol=1e-12)


@pytest.mark.slow  # about 40 s on 2 cores: fit, gradient compile, 2 x (100 + 150) NUTS steps
# (measured idle: sampling 25 s, bulk ESS 311-345, R-hat <= 1.023; 2 x (150 + 250) took 48 s)
def test_posterior_matches_the_least_squares_fit(sampled):
    status, out = sampled
    assert status == 0
    fit = json.loads((out / "result.json").read_text())["parameters"]
    posterior = json.loads((out / "posterior.json").read_text())
    report = []
    for name in TRUTH:
        p = posterior["parameters"][name]
        value, error = fit[name]["value"], fit[name]["error"]
        report.append(f"{name}: mean {p['mean']:.6g} vs {value:.6g} ({(p['mean'] - value) / error:+.2f} sigma), "
                      f"sd/error {p['sd'] / error:.3f}, ESS {p['ess']:.0f}, R-hat {p['rhat']:.3f}")
    detail = "\n".join(report)
    for name in TRUTH:
        p = posterior["parameters"][name]
        value, error = fit[name]["value"], fit[name]["error"]
        assert abs(p["mean"] - value) < 0.3 * error, detail
        assert abs(p["sd"] / error - 1) < 0.2, detail
        assert p["rhat"] < 1.05, detail
        assert p["ess"] > 100, detail
        q = p["quantiles"]
        assert q["2.5%"] < q["16%"] < q["50%"] < q["84%"] < q["97.5%"], detail
    assert posterior["divergences"] == 0
    assert 0.5 < posterior["acceptance_rate"] <= 1.0
    assert posterior["min_ess_per_s"] > 0 and posterior["sampling_time_s"] > 0


def test_chains_csv_and_corner_plot_written(sampled):
    _, out = sampled
    header = (out / "chains.csv").read_text().splitlines()[0].split(",")
    assert header == ["chain", "draw", *TRUTH]
    rows = np.loadtxt(out / "chains.csv", delimiter=",", skiprows=1)
    assert rows.shape == (2 * DRAWS, 5)
    assert sorted(set(rows[:, 0])) == [0.0, 1.0] and rows[:, 1].max() == DRAWS - 1
    assert np.all((rows[:, 3] > 900) & (rows[:, 3] < 1100))  # inside the bounds
    posterior = json.loads((out / "posterior.json").read_text())
    assert rows[:, 3].mean() == pytest.approx(posterior["parameters"]["layers.Al.thickness_um"]["mean"],
                                              rel=1e-7)
    png = (out / "corner.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000


@pytest.mark.parametrize("option", [["--sample", "0"], ["--sample", "-5"], ["--sample", "10", "--chains", "0"],
                                    ["--sample", "10", "--warmup", "3"]])
def test_bad_sampling_options_are_one_line_errors(scene_path, tmp_path, capsys, option):
    out = tmp_path / "out"
    assert main(["fit", str(scene_path), "--out", str(out), "--quiet", *option]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("fwdfit: error: --") and "\n" not in err
    assert not out.exists()


def test_sampling_a_scene_without_data_is_one_line_error(scene_path, tmp_path, capsys):
    scene = fwdfit.save_scene(small_scene(TRUTH, vary=VARY, bounds=BOUNDS), tmp_path / "scene.toml")
    out = tmp_path / "out"
    assert main(["fit", str(scene), "--out", str(out), "--quiet", "--sample", "10"]) == 1
    err = capsys.readouterr().err.strip()
    assert "no measured data" in err and "\n" not in err
    assert not out.exists()


def test_diagnostics_of_independent_and_correlated_draws():
    """Independent draws: ESS their number, R-hat 1; AR(1) draws with coefficient r:
    ESS = N (1 - r) / (1 + r); too few draws give NaN (null in posterior.json)."""
    rng = np.random.default_rng(0)
    draws, r = rng.normal(size=(4, 2000, 2)), 0.8
    for t in range(1, draws.shape[1]):
        draws[:, t, 1] = r * draws[:, t - 1, 1] + draws[:, t, 1]
    ess, rhat = diagnostics(blackjax_module(), draws)
    assert abs(ess[0] / 8000 - 1) < 0.3, ess  # the estimator's own scatter is ~10 %
    assert abs(ess[1] / (8000 * (1 - r) / (1 + r)) - 1) < 0.3, ess
    assert np.all(np.abs(rhat - 1) < 0.01), rhat
    ess, rhat = diagnostics(blackjax_module(), draws[:1, :3])
    assert np.all(np.isnan(ess)) and np.all(np.isnan(rhat))

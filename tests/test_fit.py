"""Acceptance tests of ``fwdfit.fit`` and ``fwdfit fit``: real numbers on exact synthetic data.

Synthetic measurements are made once per module by the exact reference
(``fwdfit.trace_reference``: float64 Monte Carlo, exact Snell's law), never by the
model that is fitted, plus 1 % Gaussian noise (T_err = 0.01):

- the Al block (1000 µm x 2 mm, periodictable constants for Al at 2.70 g/cm3),
  tilted by 0.24°, centred at x = 3 µm: BOA white beam at 1.1, 8.5 and 34.4 mm and
  ICON lines at 2.7 and 4.6 Å (circular 40 mm aperture at 5.5 m, 1.1 mm).

The fit starts ~20 % away from the truth in every free parameter (thickness +20 %,
SLD -20 %, mu +20 %, tilt 20 % + 0.05° off, centre 3-4 µm off). Pixel ranges are tight (they cover every pixel where
|T - T_att| > 3e-4 in the reference, plus flat open beam and sample on either side),
which keeps the fits fast. The reference's Monte Carlo noise is RMS 1-2e-3 per pixel
(at most ~2 % in a few edge pixels at 1.1 mm), well below the added 1 %.

Runtime on 2 CPU cores: tracing ~15 s, Al fit ~25 s, CLI tests ~15 s (each fit includes
its compilation).

The first version of the solver ended in wrong minima from some of these starts (tilt
~0, SLD 1.6 or 0); the fit now reads its starts off the data and scans tilt and SLD
first. ``test_fit_starts.py`` checks starts a user types, none at all, and random ones,
on the Al block and the five-layer oxide.

The CLI tests use small scenes: bad input fails before anything is compiled, and
the one successful ``fwdfit fit`` uses data made by ``fwdfit.simulate``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

import fwdfit
from fwdfit.cli import main
from helpers import BOA_SPECTRUM, gaussian_line_table, read_table, rms, small_scene, white_beam

NOISE = 0.01  # added Gaussian noise, = T_err

# --------------------------------------------------------------------------- samples

AL = fwdfit.constants_from_formula("Al", 2.70)
AL_TRUTH = {
    "sample.tilt_deg": 0.24,
    "sample.centre_um": 3.0,
    "layers.Al.thickness_um": 1000.0,
    "layers.Al.sld_e6_per_A2": AL.sld_e6_per_A2,
    "layers.Al.mu_per_m": AL.mu_per_m,
}
# Start ~20 % away from the truth in every free parameter.
AL_START = {
    "sample.tilt_deg": 0.24 * 1.2 + 0.05,  # 0.338
    "sample.centre_um": 0.0,
    "layers.Al.thickness_um": 1200.0,
    "layers.Al.sld_e6_per_A2": 0.8 * AL.sld_e6_per_A2,
    "layers.Al.mu_per_m": 1.2 * AL.mu_per_m,
}
# (name, instrument, spectrum, distance_mm, x_min_um, x_max_um, rays)
AL_PROFILES = [
    ("boa_d01.1mm", "", "white", 1.1, -800.0, 800.0, 3_000_000),
    ("boa_d08.5mm", "", "white", 8.5, -800.0, 800.0, 4_000_000),
    ("boa_d34.4mm", "", "white", 34.4, -960.0, 1104.0, 8_000_000),
    ("icon_l2.7A", "icon", "l27", 1.1, -800.0, 800.0, 3_000_000),
    ("icon_l4.6A", "icon", "l46", 1.1, -800.0, 800.0, 3_000_000),
]



BOA = dict(aperture="square", aperture_mm=40.0, aperture_distance_m=7.5)
ICON = dict(aperture="circular", aperture_mm=40.0, aperture_distance_m=5.5)
LINES = {"l27": 2.7, "l46": 4.6}
FWHM_REL = 0.15
PIXEL_UM = 2.4


# --------------------------------------------------------------------------- synthetic data


def _pixel_centres(x_min, x_max):
    n = int(round((x_max - x_min) / PIXEL_UM))
    return x_min + (np.arange(n) + 0.5) * PIXEL_UM


def _tracer_spectrum(spectrum: str):
    if spectrum == "white":
        table = read_table(BOA_SPECTRUM)
        return table["lambda_A"], table["weight"]
    return gaussian_line_table(LINES[spectrum], FWHM_REL)


def _trace(layers, tilt_deg, centre_um, profile, seed):
    """Exact reference T and T_att (n,) of one profile."""
    name, instrument, spectrum, distance_mm, x_min, x_max, rays = profile
    x = _pixel_centres(x_min, x_max)
    lam, weight = _tracer_spectrum(spectrum)
    traced = fwdfit.trace_reference(
        layers, depth_mm=2.0, tilt_deg=tilt_deg, centre_um=centre_um,
        **(ICON if instrument == "icon" else BOA), distance_mm=distance_mm,
        spectrum_lambda_A=lam, spectrum_weight=weight,
        pixel_edges_um=np.append(x - 0.5 * PIXEL_UM, x[-1] + 0.5 * PIXEL_UM),
        n_rays=rays, seed=seed)
    assert np.all(np.isfinite(traced.T)) and traced.n_dropped == 0
    return x, traced


def _write_profiles(folder: Path, profiles, layers, tilt_deg, centre_um, seed):
    """Trace, add noise, write <name>.csv (x_um,T,T_err); returns {name: (x, T_true, T_att_true, mc_err)}."""
    rng = np.random.default_rng(seed)
    truth = {}
    for i, profile in enumerate(profiles):
        x, traced = _trace(layers, tilt_deg, centre_um, profile, seed=seed + i)
        T = traced.T + rng.normal(0.0, NOISE, x.shape)
        np.savetxt(folder / f"{profile[0]}.csv", np.column_stack([x, T, np.full_like(T, NOISE)]),
                   delimiter=",", fmt="%.9g", header="x_um,T,T_err", comments="")
        truth[profile[0]] = (x, traced.T, traced.T_att, traced.T_err)
    return truth


SPECTRA = {"white": white_beam(), **{name: fwdfit.GaussianLine(w, FWHM_REL) for name, w in LINES.items()}}


def _profiles(folder: Path, profiles) -> tuple:
    return tuple(fwdfit.Profile(name, distance_mm, spectrum, instrument, _pixel_centres(x_min, x_max),
                                file=folder / f"{name}.csv")
                 for name, instrument, spectrum, distance_mm, x_min, x_max, _ in profiles)


def _sample(start: dict, layers) -> fwdfit.Sample:
    return fwdfit.Sample(depth_mm=2.0, tilt_deg=start["sample.tilt_deg"], centre_um=start["sample.centre_um"],
                         layers=tuple(layers))


def al_scene(folder: Path, start: dict) -> fwdfit.Scene:
    layer = fwdfit.Layer("Al", start["layers.Al.thickness_um"], start["layers.Al.sld_e6_per_A2"],
                         start["layers.Al.mu_per_m"], AL.mu_per_m_per_A)
    instruments = {"": fwdfit.Instrument(pixel_um=PIXEL_UM, **BOA), "icon": fwdfit.Instrument(pixel_um=PIXEL_UM, **ICON)}
    return fwdfit.Scene(_sample(start, [layer]), instruments, SPECTRA, _profiles(folder, AL_PROFILES),
                        fwdfit.FitSpec(tuple(start)))


def al_reference_layers():
    return [fwdfit.ReferenceLayer(1000.0, AL.sld_e6_per_A2, AL.mu_per_m, AL.mu_per_m_per_A)]


def make_al_case(folder: Path):
    """Scene file (starting values) and per-profile truth of the Al block."""
    folder.mkdir(parents=True, exist_ok=True)
    truth = _write_profiles(folder, AL_PROFILES, al_reference_layers(), 0.24, 3.0, seed=101)
    return fwdfit.save_scene(al_scene(folder, AL_START), folder / "scene.toml"), truth


# --------------------------------------------------------------------------- small scenes for the CLI

SMALL_TRUTH = {"sample.centre_um": 2.0, "layers.Al.thickness_um": 1000.0, "layers.Al.sld_e6_per_A2": 2.078}
SMALL_START = {"sample.centre_um": -3.0, "layers.Al.thickness_um": 1050.0, "layers.Al.sld_e6_per_A2": 1.8}


BOUNDS = {"layers.Al.thickness_um": (900.0, 1100.0)}


def small_scene_text(folder: Path, *, file="line.csv", vary=tuple(SMALL_START), bounds=BOUNDS) -> str:
    """The small scene (``helpers.small_scene``) from ``SMALL_START`` as text for ``folder``."""
    return fwdfit.dump_scene(small_scene(SMALL_START, file=file and folder / file, vary=vary, bounds=bounds),
                             folder)


def _small_table(folder: Path) -> np.ndarray:
    """(x_um, T, T_err) rows of the small scene's profile: the model at the truth + 1 % noise."""
    simulated = fwdfit.simulate(small_scene(SMALL_TRUTH))[0]
    T = simulated.T + np.random.default_rng(7).normal(0.0, NOISE, simulated.T.shape)
    return np.column_stack([simulated.x_um, T, np.full_like(T, NOISE)])


def _write_csv(path: Path, header: str, rows) -> None:
    np.savetxt(path, np.atleast_2d(rows), delimiter=",", fmt="%.9g", header=header, comments="")


@pytest.fixture(scope="module")
def small_case(tmp_path_factory):
    """A measured small scene: folder with scene.toml and line.csv; and the rows of line.csv."""
    folder = tmp_path_factory.mktemp("small")
    rows = _small_table(folder)
    _write_csv(folder / "line.csv", "x_um,T,T_err", rows)
    (folder / "scene.toml").write_text(small_scene_text(folder))
    return folder, rows


def _bad_inputs(folder: Path, rows):
    """name: (scene text for ``folder``, {csv name: (header, rows)}, words the error line must contain)."""
    def text(**options):
        return small_scene_text(folder, **options)

    ok = text()
    nan = rows.copy()
    nan[10, 1] = np.nan
    zero_err = rows.copy()
    zero_err[5, 2] = 0.0
    thickness = "layers.Al.thickness_um"
    no_profiles = text(vary=["sample.centre_um"], bounds={})
    return {
        "unknown_vary_name": (text(vary=["layers.Al.thicknes_um"], bounds={}), {},
                              ["fit.vary", "layers.Al.thicknes_um"]),
        "unknown_layer_in_vary": (text(vary=["layers.Cu.thickness_um"], bounds={}), {},
                                  ["fit.vary", "layers.Cu.thickness_um"]),
        "inverted_bounds": (text(vary=[thickness], bounds={thickness: (1100.0, 900.0)}), {},
                            ["fit.bounds", thickness]),
        "start_outside_bounds": (text(vary=[thickness], bounds={thickness: (800.0, 900.0)}), {},
                                 ["fit.bounds", thickness]),
        "bounds_not_varied": (text(vary=["sample.centre_um"], bounds={"sample.tilt_deg": (-1.0, 1.0)}), {},
                              ["fit.bounds", "sample.tilt_deg"]),
        "empty_vary": (text(vary=[], bounds={}), {}, ["fit.vary"]),
        "missing_column": (ok, {"line.csv": ("x_um,T_err", rows[:, [0, 2]])}, ["line.csv", "T"]),
        "nan_value": (ok, {"line.csv": ("x_um,T,T_err", nan)}, ["line.csv", "NaN"]),
        "single_row": (ok, {"line.csv": ("x_um,T,T_err", rows[:1])}, ["line.csv"]),
        "zero_T_err": (ok, {"line.csv": ("x_um,T,T_err", zero_err)}, ["T_err"]),
        "negative_T_err": (ok, {"line.csv": ("x_um,T,T_err", rows * [1, 1, -1])}, ["T_err"]),
        "missing_profile_file": (text(file="nowhere.csv"), {}, ["nowhere.csv"]),
        "no_measured_profile": (text(file=None), {}, ["line", "no measured data"]),
        "no_profiles_at_all": (no_profiles.split("[[profiles]]")[0] + no_profiles[no_profiles.index("[fit]"):],
                               {}, ["profiles"]),
    }


BAD_CASES = ["unknown_vary_name", "unknown_layer_in_vary", "inverted_bounds", "start_outside_bounds",
             "bounds_not_varied", "empty_vary", "missing_column", "nan_value", "single_row",
             "zero_T_err", "negative_T_err", "missing_profile_file", "no_measured_profile",
             "no_profiles_at_all"]


@pytest.mark.parametrize("case", BAD_CASES)
def test_fit_bad_input_is_one_line_error(small_case, tmp_path, capsys, case):
    """``fwdfit fit`` on bad input: exit 1, exactly one plain line on stderr naming what is
    wrong, no traceback, nothing written to --out. All of these fail before any compile."""
    _, rows = small_case
    text, tables, words = _bad_inputs(tmp_path, rows)[case]
    scene = tmp_path / "scene.toml"
    scene.write_text(text)
    _write_csv(tmp_path / "line.csv", "x_um,T,T_err", rows)
    for name, (header, table) in tables.items():
        _write_csv(tmp_path / name, header, table)
    out = tmp_path / "out"
    assert main(["fit", str(scene), "--out", str(out), "--quiet"]) == 1
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("fwdfit: error: "), lines[0]
    assert "Traceback" not in captured.err + captured.out
    for word in words:
        assert word in lines[0], (word, lines[0])
    assert not out.exists()


def test_fit_rejects_bad_starts_option(small_case, tmp_path, capsys):
    folder, _ = small_case
    out = tmp_path / "out"
    assert main(["fit", str(folder / "scene.toml"), "--out", str(out), "--quiet", "--starts", "0"]) == 1
    assert len(capsys.readouterr().err.splitlines()) == 1
    assert not out.exists()


# --------------------------------------------------------------------------- fits of exact synthetic data

@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """(result, truth, profiles) of the Al block's fit, shared by the tests below; profiles maps
    each profile name to (x_um, T_true, T_att_true, T_mc_err) of the exact reference."""
    truth = AL_TRUTH
    path, profiles = make_al_case(tmp_path_factory.mktemp("al"))
    scene = fwdfit.load_scene(path)
    for name, value in AL_START.items():  # the scene holds the starting values, not the truth
        assert _scene_value(scene, name) == pytest.approx(value)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the fit's notes are in result.warnings
        result = fwdfit.fit(scene)
    print(f"\nAl block: compile {result.compile_time_s:.1f} s, fit {result.wall_time_s:.1f} s\n"
          + _report(result, truth, profiles))
    return result, truth, profiles


def _scene_value(scene, name):
    parts = name.split(".")
    if parts[0] == "sample":
        return getattr(scene.sample, parts[1])
    layer = next(layer for layer in scene.sample.layers if layer.name == parts[1])
    return getattr(layer, parts[2])


def _report(result, truth, profiles) -> str:
    rows = [f"{'parameter':<36} {'fitted':>12} {'error':>9} {'truth':>12} {'pull':>6}"]
    for name, value, error in zip(result.names, result.values, result.errors):
        rows.append(f"{name:<36} {value:12.5f} {error:9.5f} {truth[name]:12.5f} "
                    f"{(value - truth[name]) / error:+6.2f}")
    rows.append(f"chi2_reduced {result.chi2_reduced:.4f} (dof {result.dof}), steps {result.n_steps}, "
                f"converged {result.converged}")
    for p in result.profiles:
        rows.append(f"{p.name}: RMS(T_att - T_att_true) = {rms(p.T_att - profiles[p.name][2]):.2e}")
    return "\n".join(rows)


def test_fit_converges_without_warnings(fitted):
    result, truth, _ = fitted
    assert result.converged, result.message
    assert result.warnings == ()
    assert set(result.names) == set(truth)
    assert result.dof == sum(len(p.x_um) for p in result.profiles) - len(result.names)


def test_fit_recovers_geometry(fitted):
    """Every thickness within 2 µm, the tilt within 0.02°, the centre within 1 µm."""
    result, truth, _ = fitted
    for name in result.names:
        value, _ = result[name]
        if name.endswith("thickness_um"):
            assert abs(value - truth[name]) < 2.0, (name, value)
        elif name == "sample.tilt_deg":
            assert abs(value - truth[name]) < 0.02, value
        elif name == "sample.centre_um":
            assert abs(value - truth[name]) < 1.0, value


def test_fit_recovers_sld(fitted):
    """Every fitted SLD within 5 % of the truth."""
    result, truth, _ = fitted
    slds = [n for n in result.names if n.endswith("sld_e6_per_A2")]
    assert slds
    for name in slds:
        assert result[name][0] == pytest.approx(truth[name], rel=0.05), name


def test_fit_chi2_reduced(fitted):
    """Data with 1 % noise and T_err = 0.01 fitted by a model accurate to ~1e-3: chi2_red ~ 1."""
    result, _, _ = fitted
    assert 0.8 < result.chi2_reduced < 1.3


def test_fit_attenuation_only_profile(fitted):
    """The fitted T_att matches the exact tracer's attenuation-only profile (RMS < 0.003), and
    T_corrected = T - (T_model - T_att)."""
    result, _, profiles = fitted
    for p in result.profiles:
        x, _, T_att_true, _ = profiles[p.name]
        np.testing.assert_allclose(p.x_um, x, rtol=0, atol=1e-6)
        assert rms(p.T_att - T_att_true) < 0.003, p.name
        np.testing.assert_allclose(p.T_corrected, p.T - (p.T_model - p.T_att), atol=1e-12)
        assert np.all(np.isfinite(p.T_att_err)) and np.all(p.T_att_err >= 0)


def test_fit_uncertainties_are_sensible(fitted):
    """Errors are positive and finite, the truth lies within 3 sigma of every fitted value,
    and the correlation matrix is a correlation matrix."""
    result, truth, _ = fitted
    assert np.all(np.isfinite(result.errors)) and np.all(result.errors > 0)
    pulls = {n: (v - truth[n]) / e for n, v, e in zip(result.names, result.values, result.errors)}
    assert all(abs(p) < 3.0 for p in pulls.values()), pulls
    c = result.correlation
    np.testing.assert_allclose(np.diag(c), 1.0, atol=1e-9)
    np.testing.assert_allclose(c, c.T, atol=1e-12)
    assert np.all(np.abs(c) <= 1.0 + 1e-9)


def test_fitted_scene_holds_fitted_values(fitted):
    result, _, _ = fitted
    for name, value in zip(result.names, result.values):
        assert _scene_value(result.scene, name) == pytest.approx(value, rel=1e-12, abs=1e-12)
    if any(layer.same_as for layer in result.scene.sample.layers):  # ties keep both sides equal
        layers = {layer.name: layer for layer in result.scene.sample.layers}
        for layer in result.scene.sample.layers:
            if layer.same_as:
                twin = layers[layer.same_as]
                assert (layer.thickness_um, layer.sld_e6_per_A2, layer.mu_per_m) == (
                    twin.thickness_um, twin.sld_e6_per_A2, twin.mu_per_m)


# --------------------------------------------------------------------------- fwdfit fit: output files


def test_fit_cli_writes_results(small_case, tmp_path, capsys):
    """``fwdfit fit`` on a small measured scene: exit 0; result.json with the SCENE.md keys;
    <profile>.csv with x_um,T,T_model,T_att,T_corrected; <profile>.png; fitted_scene.toml,
    which ``load_scene`` reads back with the fitted values (round trip)."""
    folder, rows = small_case
    out = tmp_path / "out"
    assert main(["fit", str(folder / "scene.toml"), "--out", str(out), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    assert sorted(p.name for p in out.iterdir()) == [".fwdfit-output", "fitted_scene.toml", "line.csv", "line.png",
                                                     "result.json"]

    result = json.loads((out / "result.json").read_text())
    assert set(result["parameters"]) == set(SMALL_TRUTH)
    for name, entry in result["parameters"].items():
        assert set(entry) >= {"value", "error"}
        assert math.isfinite(entry["value"]) and entry["error"] > 0
        # model-made data: only the noise moves the values
        assert abs(entry["value"] - SMALL_TRUTH[name]) < 4 * entry["error"], (name, entry)
    assert result["converged"] is True
    assert 0.8 < result["chi2_reduced"] < 1.2
    assert result["wall_time_s"] > 0

    table = read_table(out / "line.csv")
    header = (out / "line.csv").read_text().splitlines()[0].split(",")
    assert header[:5] == ["x_um", "T", "T_model", "T_att", "T_corrected"]
    np.testing.assert_allclose(table["x_um"], rows[:, 0], rtol=1e-9)
    np.testing.assert_allclose(table["T"], rows[:, 1], rtol=1e-8)
    np.testing.assert_allclose(table["T_corrected"], table["T"] - (table["T_model"] - table["T_att"]),
                               atol=1e-8)
    assert rms(table["T"] - table["T_model"]) < 1.2 * NOISE
    assert (out / "line.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    fitted = fwdfit.load_scene(out / "fitted_scene.toml")
    for name, entry in result["parameters"].items():
        assert _scene_value(fitted, name) == pytest.approx(entry["value"], rel=1e-12)
    assert fitted.fit.vary == tuple(SMALL_START)
    assert fitted.fit.bounds == {"layers.Al.thickness_um": (900.0, 1100.0)}
    np.testing.assert_allclose(fitted.profiles[0].T, rows[:, 1], rtol=1e-8)  # same data file


def test_a_parameter_pinned_at_its_bound_is_reported(tmp_path):
    """A scene whose 1/v attenuation alone exceeds what the data show (mu_per_m_per_A 5 /m/Å
    where the data's Al has 0.774) drives the free mu_per_m to its lower bound 0: the fit says
    so in its warnings instead of reporting the bound as a measured value."""
    _write_csv(tmp_path / "line.csv", "x_um,T,T_err", _small_table(tmp_path))
    scene = small_scene(SMALL_TRUTH, file=tmp_path / "line.csv", vary=["layers.Al.mu_per_m"])
    heavy = dataclasses.replace(scene.sample.layers[0], mu_per_m_per_A=5.0)
    scene = dataclasses.replace(scene, sample=dataclasses.replace(scene.sample, layers=(heavy,)))
    path = fwdfit.save_scene(scene, tmp_path / "scene.toml")
    with pytest.warns(UserWarning, match="pinned at its lower bound"):
        result = fwdfit.fit(path)
    (value,) = result.values
    assert value < 0.1 * result.errors[0]
    assert any("layers.Al.mu_per_m" in w and "pinned at its lower bound 0" in w for w in result.warnings)

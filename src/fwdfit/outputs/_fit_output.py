"""Fit results to files: result.json, per-profile CSVs, PNG plots, and the fitted scene."""

from __future__ import annotations

import json
import platform
from pathlib import Path

import numpy as np

from ..scene import _registry as registry
from .._errors import FwdfitError
from ..inference._fit import FitResult
from ..scene._scene_toml import dump_scene
from ..scene._spectrum import BandSpectrum, GaussianLine
from ..io._tables import staged_folder, write_columns
from ._plotting import draw_error_band
from ._tof_output import write_tof

MAX_PROFILE_PLOTS = 24  # <profile>.png for at most this many profiles, evenly spread over the list


def result_dict(result: FitResult) -> dict:
    """Everything result.json holds: values, errors, correlations, chi-square, timings, versions."""
    import equinox
    import jax
    import optimistix

    from .._version import __version__

    return {
        "parameters": {name: {"value": float(v), "error": float(e), "unit": registry.unit(name)}
                       for name, v, e in zip(result.names, result.values, result.errors)},
        "correlation": {"names": list(result.names), "matrix": np.round(result.correlation, 6).tolist()},
        "chi2": result.chi2,
        "dof": result.dof,
        "chi2_reduced": result.chi2_reduced,
        "chi2_per_start": [float(c) if np.isfinite(c) else None for c in result.chi2_per_start],
        "sigma_from_data": result.sigma_from_data,
        "converged": result.converged,
        "accepted": result.accepted,
        "message": result.message,
        "quality": quality_dict(result.quality),
        "start_from_data": {name: (float(v) if np.isfinite(v) else None) for name, v in result.start.items()},
        "iterations": result.n_steps,
        "model_evaluations": result.n_evaluations,
        "compile_time_s": result.compile_time_s,
        "solve_time_s": result.wall_time_s,
        "wall_time_s": result.compile_time_s + result.wall_time_s,
        "warnings": list(result.warnings),
        "model_warnings": list(result.model_warnings),
        "versions": {"fwdfit": __version__, "jax": jax.__version__, "equinox": equinox.__version__,
                     "optimistix": optimistix.__version__, "python": platform.python_version()},
    }


def quality_dict(quality) -> dict:
    """The quality gate's verdict: passed, one line, chi-square per profile, failing regions."""
    def region(r):
        return {"profile": r.profile, "where": r.what, "x_from_um": r.x_from_um, "x_to_um": r.x_to_um,
                "pixels": r.n, "chi2_reduced": r.chi2_reduced, "mean_residual_sigma": r.mean_z / max(r.n, 1) ** 0.5,
                "runs_z": r.runs_z}

    return {"passed": quality.passed, "summary": quality.summary(),
            "chi2_reduced_per_profile": {r.profile: r.chi2_reduced for r in quality.profiles},
            "failing": [region(r) for r in quality.failing]}


def spectrum_label(spectrum) -> str:
    """A spectrum's wavelength or band as a title says it, in Å."""
    if isinstance(spectrum, GaussianLine):
        return f"λ {spectrum.wavelength_A:.3g} Å (FWHM {100 * spectrum.fwhm_rel:.3g} %)"
    if isinstance(spectrum, BandSpectrum):
        return f"λ {spectrum.lambda_min_A:.4g}-{spectrum.lambda_max_A:.4g} Å"
    low, high = spectrum.support_A
    return f"white beam λ {low:.3g}-{high:.3g} Å (mean {spectrum.mean_wavelength_A:.3g} Å)"


def verdict(result: FitResult) -> str:
    """"accepted", or "rejected" and why: the solver did not converge, or the data reject the fit."""
    if result.accepted:
        return "accepted"
    return "rejected (not converged)" if not result.converged else "rejected by the data"


def profile_title(result: FitResult, index: int) -> str:
    """Two lines: the profile's name, distance and wavelength or band; the fit's chi2/dof,
    the profile's own chi2 per pixel and the verdict."""
    profile = result.scene.profiles[index]
    spectrum = spectrum_label(result.scene.spectra[profile.spectrum])
    line = f"{profile.name}: distance {profile.distance_mm:g} mm, {spectrum}"
    own = {r.profile: r.chi2_reduced for r in result.quality.profiles}.get(profile.name)
    here = "" if own is None else f", this profile χ²/pixel {own:.3f}"
    return f"{line}\nfit χ²/dof {result.chi2_reduced:.3f} (dof {result.dof}){here}: {verdict(result)}"


class ProfilePlot:
    """Data with fit and residuals (top), attenuation-only fit against corrected data (bottom),
    legends right of the axes, the title from :func:`profile_title`.

    One ``Figure`` of its own (pyplot's state and backend are left alone), built once and
    drawn again for each profile: its axes and ticks cost more than the drawing (0.35 s a
    plot when each profile builds its own, 0.15 s when they share one).
    """

    def __init__(self, result: FitResult):
        from matplotlib.figure import Figure

        self.result = result
        self.figure = fig = Figure(figsize=(10, 8), dpi=100)
        self.axes = top, middle, bottom = fig.subplots(3, 1, sharex=True,
                                                       gridspec_kw={"height_ratios": [3, 1, 3]})
        fig.subplots_adjust(left=0.1, right=0.7, top=0.92, bottom=0.07, hspace=0.08)  # tight_layout: 3x slower
        (self.measured,) = top.plot([], [], ".", ms=2, color="0.4", label="measured T")
        (self.model,) = top.plot([], [], "-", lw=1, color="C3", label="fit T_model")
        top.set_ylabel("transmission T, T_model")
        (self.residual,) = middle.plot([], [], ".", ms=2, color="C0")
        middle.axhline(0, color="k", lw=0.5)
        middle.set_ylabel("(T - T_model) / σ")
        (self.corrected,) = bottom.plot([], [], ".", ms=2, color="0.4",
                                        label="T_corrected = T - (T_model - T_att)\n(data, refraction removed)")
        (self.attenuation,) = bottom.plot([], [], "-", lw=1, color="C2")
        bottom.set_ylabel("T_corrected, T_att")
        bottom.set_xlabel("x (µm)")

    def draw(self, index: int):
        """Draw the result's profile ``index`` and return the ``Figure``."""
        profile = self.result.profiles[index]
        top, middle, bottom = self.axes
        for band in bottom.collections[:]:
            band.remove()
        x = profile.x_um
        self.measured.set_data(x, profile.T)
        self.model.set_data(x, profile.T_model)
        self.residual.set_data(x, (profile.T - profile.T_model) / profile.sigma)
        self.corrected.set_data(x, profile.T_corrected)
        self.attenuation.set_data(x, profile.T_att)
        for axes in self.axes:
            axes.relim()
            axes.autoscale_view()
        draw_error_band(bottom, self.attenuation, profile.T_att_err, "T_att (attenuation-only fit)")
        for axes in (top, bottom):
            axes.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8)
        top.set_title(profile_title(self.result, index), fontsize=9, loc="left",
                      color="black" if self.result.accepted else "tab:red")
        return self.figure

    def save(self, path: Path, index: int):
        """Draw the result's profile ``index``, write it to ``path`` (PNG), return the ``Figure``."""
        figure = self.draw(index)
        figure.savefig(path, pil_kwargs={"compress_level": 1})  # zlib 6: +50 ms a plot
        return figure


def write_fit(result: FitResult, out_dir: Path) -> None:
    """Write result.json, <profile>.csv, <profile>.png (at most ``MAX_PROFILE_PLOTS``),
    fitted_scene.toml and, for time-of-flight bins, ``_tof_output``'s files into out_dir.

    Everything is written into a temporary folder first and moved into place, so an
    error (a NaN or infinite value anywhere, which strict JSON cannot hold) or Ctrl-C
    leaves ``out_dir`` without partial results.
    """
    out_dir = Path(out_dir)
    try:
        summary = json.dumps(result_dict(result), indent=2, allow_nan=False) + "\n"
    except ValueError:
        raise FwdfitError("result.json: a value is NaN or infinite; nothing written "
                          "(please report this scene)") from None
    with staged_folder(out_dir) as staging:
        (staging / "result.json").write_text(summary)
        plotted = set(np.linspace(0, len(result.profiles) - 1, MAX_PROFILE_PLOTS).round().astype(int).tolist()
                      if len(result.profiles) > MAX_PROFILE_PLOTS else range(len(result.profiles)))
        for p in result.profiles:  # every table first: a NaN stops the write before any plot is drawn
            write_columns(staging / f"{p.name}.csv", {
                "x_um": p.x_um, "T": p.T, "T_model": p.T_model, "T_att": p.T_att,
                "T_corrected": p.T_corrected, "T_att_err": p.T_att_err})
        plot = ProfilePlot(result) if plotted else None
        for i in sorted(plotted):
            plot.save(staging / f"{result.profiles[i].name}.png", i)
        write_tof(result, staging)
        (staging / "fitted_scene.toml").write_text(dump_scene(result.scene, out_dir, comment="written by fwdfit"))

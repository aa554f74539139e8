"""``fwdfit design``'s files: design.json, design.csv and design.png."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from ..inference._design import Design
from ..io._tables import staged_folder
from ..scene._registry import unit


def design_dict(d: Design) -> dict:
    """The plans (exposure per measurement, those used only) and their predicted standard
    errors, every shared parameter, targets first."""
    def errors(plan):
        return {name: _finite(e) for name, e in zip(d.parameters, d.errors(plan))}

    plans = {name: {"measurements": [{"spectrum": c.spectrum, "instrument": c.instrument or "default",
                                      "distance_mm": c.distance_mm, "exposure": float(t)}
                                     for c, t in zip(d.candidates, plan) if t > 0],
                    "errors": errors(plan)} for name, plan in d.plans.items()}
    target_errors = {name: d.errors(plan)[list(d.targets)] for name, plan in d.plans.items()}
    gain = {f"optimal_vs_{name}": _finite(float(np.max(target_errors[name] / target_errors["optimal"])))
            for name in d.plans if name != "optimal"}
    return {"targets": [d.parameters[i] for i in d.targets],
            "values": dict(zip(d.parameters, map(float, d.values))),
            "units": {name: unit(name) for name in d.parameters},
            "exposure": d.budget, "noise": d.noise, "plans": plans,
            "error_ratio": gain}


def _finite(value: float) -> float | None:
    """A JSON number, None for an undetermined (infinite) error."""
    return float(value) if math.isfinite(value) else None


def write_design(d: Design, out_dir: Path) -> None:
    """Write design.json (``design_dict``), design.csv (one line per candidate: its exposure
    in each plan and the targets' errors with the whole budget on it alone) and design.png
    (those errors against distance, one line per spectrum, the plans' errors as levels)."""
    summary = json.dumps(design_dict(d), indent=2, allow_nan=False) + "\n"
    alone = d.single_errors()[:, list(d.targets)]
    targets = [d.parameters[i] for i in d.targets]
    with staged_folder(Path(out_dir)) as staging:
        (staging / "design.json").write_text(summary)
        with open(staging / "design.csv", "x", newline="", encoding="utf-8") as stream:
            table = csv.writer(stream)
            table.writerow(["spectrum", "instrument", "distance_mm", *(f"exposure_{name}" for name in d.plans),
                            *(f"alone_err_{name}" for name in targets)])
            for i, c in enumerate(d.candidates):
                table.writerow([c.spectrum, c.instrument or "default", f"{c.distance_mm:g}",
                                *(f"{plan[i]:.6g}" for plan in d.plans.values()),
                                *(f"{e:.6g}" for e in alone[i])])
        _plot(d, alone, targets).savefig(staging / "design.png", dpi=100)


def _plot(d: Design, alone: np.ndarray, targets: list[str]):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, len(targets), figsize=(5.2 * len(targets) + 3.4, 4.2), squeeze=False)
    spectra = list(dict.fromkeys(c.spectrum for c in d.candidates))
    for k, (ax, name) in enumerate(zip(axes[0], targets)):
        for spectrum in spectra:
            rows = sorted((c.distance_mm, alone[i, k]) for i, c in enumerate(d.candidates) if c.spectrum == spectrum)
            x, y = np.array(rows).T
            ax.plot(x, np.where(np.isfinite(y), y, np.nan), "o-", label=f"{spectrum}, whole exposure at one distance")
        for (plan_name, plan), style in zip(d.plans.items(), ("-", "--", ":")):
            ax.axhline(d.errors(plan)[d.targets[k]], color="k", ls=style, lw=1, label=f"plan: {plan_name}")
        ax.set(xscale="log", yscale="log", xlabel="sample-detector distance (mm)",
               ylabel=f"predicted σ of {name} ({unit(name)})", title=f"{name}, exposure {d.budget:g}")
    axes[0][-1].legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8)
    figure.tight_layout()
    return figure


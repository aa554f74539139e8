"""Simulate every profile of a scene: the library side of ``fwdfit simulate``."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ._geometry import geometry_of
from ._parameters import assembler
from ._predict import Predictor
from .._progress import Progress, as_progress
from ..scene._scene import Scene, load_scene
from ..io._tables import check_finite, staged_folder, write_columns


@dataclasses.dataclass(frozen=True)
class SimulatedProfile:
    """Pixel centres x_um (n,), transmission T (n,) and attenuation-only T_att (n,)."""

    name: str
    x_um: np.ndarray
    T: np.ndarray
    T_att: np.ndarray


def simulate(scene: Scene | str | Path, accuracy: float | None = None,
             progress: bool | Progress = False) -> list[SimulatedProfile]:
    """T and T_att for every profile of a scene (a ``Scene`` or a scene file path).

    accuracy: target RMS error in T, in the validity domain [1e-5, 0.1]; default the
    scene's ``[model] accuracy``. FwdfitError if any value comes out NaN or infinite.
    The model's programs come from the cache folder where ``enable_compilation_cache``
    set one (``_predict``). progress: say what happens on stderr.
    """
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    say = as_progress(progress)
    model = geometry_of(scene).build_model(scene, accuracy, (), None)
    assemble = assembler(scene, ())
    say(f"model planned; preparing it: {len(scene.profiles)} profiles in {len(model.groups)} programs")
    with say.ticking("compiling"):
        predict = Predictor(model, assemble, 0)
    say(f"model ready in {predict.compile_time_s:.1f} s ({predict.sources_text()})")
    (T,), (T_att,) = predict(np.zeros((1, 0)))
    ends = np.cumsum([len(p.x_um) for p in scene.profiles])[:-1]
    profiles = [SimulatedProfile(p.name, p.x_um, t, a)
                for p, t, a in zip(scene.profiles, np.split(T, ends), np.split(T_att, ends))]
    for p in profiles:
        check_finite({"T": p.T, "T_att": p.T_att}, f"{scene.path}: profile {p.name!r}")
    return profiles


def write_simulation(profiles: list[SimulatedProfile], out_dir: Path, notes: Sequence[str] = ()) -> None:
    """Write ``out_dir/<name>.csv`` with columns x_um,T,T_att for each profile and, if there are
    any, the model's notes (its ``ModelWarning`` messages) one per line to ``warnings.txt``
    (all or none)."""
    with staged_folder(out_dir) as staging:
        for p in profiles:
            write_columns(staging / f"{p.name}.csv", {"x_um": p.x_um, "T": p.T, "T_att": p.T_att})
        if notes:
            (staging / "warnings.txt").write_text("".join(f"{note}\n" for note in notes))

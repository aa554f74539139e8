"""The forward model against every shipped reference profile: McStas and the exact ray tracer.

Each case is a scene in ``tests/data`` that restates the reference run (see
``tests/data/PROVENANCE.md``); the model runs it with default settings (accuracy 1e-3)
and must match, per profile:

- the transmission T and the attenuation-only T_att to an RMS difference of 0.002
  (the references' own noise is 0.00004-0.0006 RMS; measured model differences are
  0.0001-0.0007 in T and below 0.0004 in T_att, see benchmarks/reference_table.md);
- the gain-peak height and the loss-dip depth at each edge to 5 % (definitions in
  ``helpers.edge_heights``: extrema after a running mean over an eighth of the
  penumbra, loss measured from the reference's T_att; measured worst 3.4 %).

Every scene's model is built and run once per module (about 50 s for all eight
scenes, 43 profiles, mostly compilation).
"""

from pathlib import Path

import equinox as eqx
import numpy as np
import pytest
import tomllib

import fwdfit
from helpers import (MCSTAS, RAYTRACE, REFERENCE_SCENES as SCENES, edge_heights, load_reference, rms,
                     smoothing_pixels)

RMS_TOLERANCE = 0.002
PEAK_RTOL = 0.05


def _profile_names(path: Path) -> list[str]:
    with open(path, "rb") as stream:
        return [p["name"] for p in tomllib.load(stream)["profiles"]]


CASES = [(case, name) for case, path in SCENES.items() for name in _profile_names(path)]
CASE_IDS = [f"{case}/{name}" for case, name in CASES]


@pytest.fixture(scope="module")
def predictions():
    """``predictions(case)`` -> (scene, {profile name: (T, T_att)}), each scene run once."""
    cache = {}

    def get(case):
        if case not in cache:
            scene = fwdfit.load_scene(SCENES[case])
            T, T_att = eqx.filter_jit(fwdfit.build_model(scene))(fwdfit.initial_params(scene))
            cache[case] = scene, {p.name: (np.asarray(t), np.asarray(a))
                                  for p, t, a in zip(scene.profiles, T, T_att)}
        return cache[case]

    return get


def _reference(case, name):
    return load_reference(SCENES[case].parent, name)


def test_every_reference_file_is_covered():
    """Each reference CSV of tests/data belongs to one profile checked here (none skipped)."""
    covered = {SCENES[case].parent / f"{name}.csv" for case, name in CASES}
    shipped = {p for p in MCSTAS.glob("*.csv")
               if not p.name.startswith("spectrum") and "attenuation_only" not in p.name}
    shipped |= {p for p in RAYTRACE.glob("*/*.csv") if not p.name.startswith("spectrum")}
    assert shipped == covered
    assert len(CASES) == 43


@pytest.mark.parametrize("case, name", CASES, ids=CASE_IDS)
def test_transmission_rms(predictions, case, name):
    """RMS(T - T_ref) over the whole profile is at most 0.002 (same pixel grid as the reference)."""
    scene, result = predictions(case)
    ref = _reference(case, name)
    (profile,) = [p for p in scene.profiles if p.name == name]
    np.testing.assert_allclose(profile.x_um, ref["x_um"], rtol=0, atol=1e-6)
    T, _ = result[name]
    assert rms(T - ref["T"]) <= RMS_TOLERANCE


@pytest.mark.parametrize("case, name", CASES, ids=CASE_IDS)
def test_attenuation_only_rms(predictions, case, name):
    """RMS(T_att - T_att_ref) is at most 0.002; T_att_ref is McStas' attenuation-only run
    (coherent cross-section moved to incoherent) or the tracer's no-SLD rays."""
    _, result = predictions(case)
    ref = _reference(case, name)
    _, T_att = result[name]
    assert rms(T_att - ref["T_att"]) <= RMS_TOLERANCE
    assert T_att.min() < 0.999  # the sample is in the field of view


@pytest.mark.parametrize("case, name", CASES, ids=CASE_IDS)
def test_edge_peaks(predictions, case, name):
    """Gain-peak height and loss-dip depth at both edges within 5 % of the reference's.

    Heights as in ``helpers.edge_heights``, with the same smoothing width and the same
    baseline (the reference's T_att) for model and reference. Every reference peak is at
    least 0.018 high after smoothing, so 5 % is at least 0.0009 in T.
    """
    scene, result = predictions(case)
    ref = _reference(case, name)
    (profile,) = [p for p in scene.profiles if p.name == name]
    instrument = scene.instruments[profile.instrument]
    n = smoothing_pixels(profile.distance_mm, instrument.aperture_mm,
                         instrument.aperture_distance_m, instrument.pixel_um)
    T, _ = result[name]
    centre = scene.sample.centre_um
    mine = np.array(edge_heights(ref["x_um"], T, ref["T_att"], centre, n))
    theirs = np.array(edge_heights(ref["x_um"], ref["T"], ref["T_att"], centre, n))
    assert np.all(theirs > 0.01)
    np.testing.assert_allclose(mine, theirs, rtol=PEAK_RTOL, atol=0)

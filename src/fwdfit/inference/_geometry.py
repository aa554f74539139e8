"""The geometries a scene may name, behind one seam (``model._geometry.Geometry``).

``geometry_of`` picks a scene's shape by its ``[sample] geometry``; a new shape
implements the protocol in its own folder of ``model/`` and is one entry of
``GEOMETRIES``. The layered block (flat layers side by side along x, tilted about the
vertical axis: ``model/block``, the starts of ``_starts``) is implemented here, since
its starts sit in ``inference/``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..model._geometry import Geometry as Geometry
from ..model._geometry import edge_half_width_um
from ..model.block._plan import build_model, initial_params
from ..model.cylinder import Cylinder
from ..scene import _registry as registry
from ._starts import SLD_VALUE_MAX, estimate, narrow_profiles, refraction_reach_um


class LayeredBlock:
    """Flat layers side by side along x, depth along the beam, tilted about the vertical axis."""

    def initial_params(self, scene, dtype=None):
        return initial_params(scene, dtype)

    def plan_scene(self, scene, free):
        """Missing start values filled: an unknown SLD at the largest value the global scan
        tries (kernel windows are sized for it; the plan's margin for free parameters covers
        the scan's factors on a known one), an unknown thickness at 0 (not a coupled thin
        layer), any other at 1; an unknown tilt and centre at 0."""
        layers = list(scene.sample.layers)
        for p in free:
            field, index = p.target
            for i in index if registry.BY_KEY[field].part == "layers" else ():
                value = getattr(layers[i], field)
                if field == "sld_e6_per_A2":
                    value = SLD_VALUE_MAX if math.isnan(value) else value
                elif field == "thickness_um" and math.isnan(value):
                    value = 0.0  # unknown: planned with independent faces (``_plan.thin_layers``)
                elif math.isnan(value):
                    value = 1.0
                layers[i] = dataclasses.replace(layers[i], **{field: value})
        sample = scene.sample
        if math.isnan(sample.tilt_deg):
            sample = dataclasses.replace(sample, tilt_deg=0.0)
        if math.isnan(sample.centre_um):
            sample = dataclasses.replace(sample, centre_um=0.0)
        return dataclasses.replace(scene, sample=dataclasses.replace(sample, layers=tuple(layers)))

    def build_model(self, scene, accuracy, free, tilt_range_deg):
        return build_model(scene, accuracy, free=free, tilt_range_deg=tilt_range_deg)

    def estimate(self, scene, free, T, model):
        return estimate(scene, free, T, model)

    def check_data(self, scene, T):
        """Profiles narrower than the stack need every layer's thickness (``narrow_profiles``)."""
        narrow_profiles(scene, T)

    def at_tilts(self, free, estimate, row, tilts_deg):
        """The data pin each layer's projected width t / cos(tilt): thicknesses follow the tilt."""
        names = [p.name for p in free]
        tilt = names.index("sample.tilt_deg")
        thickness = [names.index(n) for n in estimate.thickness_names]
        projected = row[thickness] / math.cos(math.radians(row[tilt]))
        rows = np.repeat(row[None], len(tilts_deg), axis=0)
        rows[:, tilt] = tilts_deg
        rows[:, thickness] = projected[None] * np.cos(np.radians(tilts_deg))[:, None]
        return rows

    def plateau(self, scene, profile):
        """Pixels inside the thickest layer, farther from its faces (at the mid-plane, and carried
        along the tilt to the detector) than the refraction reach plus the tilt's spread over
        the depth."""
        sample = scene.sample
        thickness = np.array([l.thickness_um for l in sample.layers])
        tilt = math.radians(sample.tilt_deg)
        bounds = np.concatenate([[0.0], np.cumsum(thickness)]) - 0.5 * thickness.sum()
        bounds = (sample.centre_um + profile.shift_um + sample.drift_um_per_mm * profile.distance_mm
                  + bounds / math.cos(tilt))
        carried = 1e3 * profile.distance_mm * math.tan(tilt)  # refracted rays land about the faces carried along
        thickest = int(np.argmax(thickness))
        margin = refraction_reach_um(scene, profile) + 0.5e3 * sample.depth_mm * abs(math.tan(tilt))
        low = max(bounds[thickest], bounds[thickest] + carried) + margin
        high = min(bounds[thickest + 1], bounds[thickest + 1] + carried) - margin
        return (profile.x_um > low) & (profile.x_um < high)

    def interfaces(self, scene, profile):
        """Each face from its upstream to its downstream end, projected along the beam, and the
        edge half width from the penumbra, the detector blur and the depth's sideways spread."""
        sample, instrument = scene.sample, scene.instruments[profile.instrument]
        tilt = math.radians(sample.tilt_deg)
        cumulative = np.concatenate([[0.0], np.cumsum([l.thickness_um for l in sample.layers])])
        across = (cumulative - 0.5 * cumulative[-1]) / math.cos(tilt)
        media = ["vacuum"] + [l.name for l in sample.layers] + ["vacuum"]
        centre = sample.centre_um + profile.shift_um + sample.drift_um_per_mm * profile.distance_mm
        slope_um = profile.distance_mm * 1e3 * math.tan(tilt)
        faces = [(centre + a, centre + a + slope_um, f"{media[k]} | {media[k + 1]}") for k, a in enumerate(across)]
        penumbra = profile.distance_mm * instrument.aperture_mm / instrument.aperture_distance_m
        spread = 0.5 * sample.depth_mm * 1e3 * abs(math.tan(tilt))
        return faces, edge_half_width_um(profile.distance_mm, penumbra, instrument.psf_fwhm_um, spread)

    def sized_for(self, scene, width_um):
        """An unknown thickness at an equal share of half the window."""
        layers = scene.sample.layers
        filled = tuple(dataclasses.replace(l, thickness_um=0.5 * width_um / len(layers))
                       if math.isnan(l.thickness_um) else l for l in layers)
        return dataclasses.replace(scene, sample=dataclasses.replace(scene.sample, layers=filled))

    def undetermined(self, scene, names, in_view):
        """A thickness without a face in view on each side of its layer (face i: layer i's
        left face), a layer's SLD without either of its faces in view (a layer ``same_as``
        another counts for it)."""
        layers = scene.sample.layers
        faces = np.flatnonzero(in_view)
        out = []
        for name in names:
            parts = name.split(".")
            if parts[0] != "layers":
                continue
            j = next((i for i, layer in enumerate(layers) if layer.name == parts[1]), None)
            if j is None:
                continue
            same = [i for i, layer in enumerate(layers) if i == j or layer.same_as == layers[j].name]
            key = parts[-1]
            if key == "thickness_um":
                ok = any(faces.size and faces.min() <= i and faces.max() >= i + 1 for i in same)
            elif key in ("sld_e6_per_A2", "sld_end_e6_per_A2", "roughness_mrad"):
                ok = any(in_view[i] or in_view[i + 1] for i in same)
            else:
                continue
            if not ok:
                out.append(name)
        return out


GEOMETRIES = {"block": LayeredBlock, "cylinder": Cylinder}  # a scene's [sample] geometry -> its shape


def geometry_of(scene) -> Geometry:
    """The geometry of a scene (its ``[sample] geometry``; the layered block by default)."""
    return GEOMETRIES[getattr(scene.sample, "geometry", "block")]()

"""Concentric shells about an axis along the detector's columns: rods and tubes.

``build_model`` plans a cylinder scene into a ``CylinderModel`` of ``CylinderParams``;
``trace`` and ``chords`` are the exact rays through the circles."""

from ._geometry import Cylinder as Cylinder
from ._model import CylinderModel as CylinderModel
from ._model import CylinderParams as CylinderParams
from ._plan import build_model as build_model
from ._plan import initial_params as initial_params
from ._rays import chords as chords
from ._rays import trace as trace

"""The layered block, today's one geometry: its plan (``build_model``, ``initial_params``,
``fresnel_nodes``), its ``ForwardModel`` of ``ModelParams``, the coupled thin layers, and
what the free parameters take from it (``layer_value``, ``to_device``)."""

from ._model import DEPTH_PIECES as DEPTH_PIECES
from ._model import ForwardModel as ForwardModel
from ._model import ModelParams as ModelParams
from ._plan import build_model as build_model
from ._plan import fresnel_nodes as fresnel_nodes
from ._plan import initial_params as initial_params
from ._plan import layer_value as layer_value
from ._plan import to_device as to_device

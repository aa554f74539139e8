"""fwdfit: differentiable forward-model fitting of refraction at interfaces in neutron radiographs."""

from ._errors import FwdfitError as FwdfitError

__version__ = "0.1.0"

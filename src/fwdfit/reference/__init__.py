"""The exact Monte Carlo tracers: float64 NumPy, exact Snell's law at every face, the
independent references the forward model is tested against (tests/data/PROVENANCE.md):
layered blocks (``trace_reference``) and concentric circles, rods and tubes
(``trace_cylinder_reference``)."""

from ._cylinder_reference import trace_cylinder_reference as trace_cylinder_reference
from ._reference import ReferenceLayer as ReferenceLayer
from ._reference import ReferenceResult as ReferenceResult
from ._reference import trace_reference as trace_reference
from ._reference import trace_reference_rows as trace_reference_rows
from ._spectra import maxwellian_spectrum as maxwellian_spectrum

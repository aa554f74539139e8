"""The exact Monte Carlo tracer: float64 NumPy, exact Snell's law at every face, the
independent reference the forward model is tested against (tests/data/PROVENANCE.md)."""

from ._reference import ReferenceLayer as ReferenceLayer
from ._reference import trace_reference as trace_reference
from ._reference import trace_reference_rows as trace_reference_rows

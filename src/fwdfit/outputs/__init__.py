"""A fit's files: ``write_fit`` (result.json, the fitted scene, one CSV and plot per
profile, the time-of-flight spectrum table ``write_tof``) and ``write_posterior`` (a
sampler's draws and corner plot)."""

from ._fit_output import ProfilePlot as ProfilePlot
from ._fit_output import write_fit as write_fit
from ._sample_output import write_posterior as write_posterior
from ._tof_output import write_tof as write_tof

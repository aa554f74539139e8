"""Files in and out, below the scene: the CSV tables profiles, spectra and results are read
from and written to (written whole or not at all), and the time-of-flight stacks (FITS
folders, HDF5/NeXus files) that ``fwdfit profile --tof`` reads."""

from ._tables import read_columns as read_columns
from ._tables import write_columns as write_columns
from ._tof_read import TofStack as TofStack
from ._tof_read import open_tof_stack as open_tof_stack

"""Images to profiles and image fits: TIFF stacks to a normalised profile
(``profile_from_stacks`` and its steps), one image fitted row by row (``fit_image``,
``edge_centres``, the row flags) and a series of images (``fit_series``, serial or Dask)."""

from ._image_fit import FLAG_MASKED as FLAG_MASKED
from ._image_fit import FLAG_NO_EDGE as FLAG_NO_EDGE
from ._image_fit import FLAG_NOT_CONVERGED as FLAG_NOT_CONVERGED
from ._image_fit import FLAG_POOR_FIT as FLAG_POOR_FIT
from ._image_fit import ImageFit as ImageFit
from ._image_fit import edge_centres as edge_centres
from ._image_fit import fit_image as fit_image
from ._image_series import OUTPUT_FILES as OUTPUT_FILES
from ._image_series import fit_series as fit_series
from ._image_series import local_client as local_client
from ._radiograph import Roi as Roi
from ._radiograph import clipped_mean_frames as clipped_mean_frames
from ._radiograph import combine_frames as combine_frames
from ._radiograph import edge_angle_deg as edge_angle_deg
from ._radiograph import frame_layout as frame_layout
from ._radiograph import iter_frame_rows as iter_frame_rows
from ._radiograph import plot_radiograph_png as plot_radiograph_png
from ._radiograph import profile_from_stacks as profile_from_stacks
from ._radiograph import remove_spots as remove_spots
from ._radiograph import sheared_roi as sheared_roi
from ._radiograph import tiff_files as tiff_files
from ._radiograph import write_profile_csv as write_profile_csv

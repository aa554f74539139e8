"""Time-of-flight stacks: one image per time bin, from FITS folders or NeXus/HDF5 files.

Two layouts, as the instruments write them:

- **FITS folder** (MCP/Timepix cameras, e.g. ISIS IMAT): one FITS image per bin
  (``run_00000.fits``, ``run_00001.fits``, ...) and one ``*_Spectra.txt`` beside them,
  a headerless table (tabs or spaces, any line ending) whose first column is each
  bin's time of flight in seconds (the second, counts, is not used). The camera's
  ``*_SummedImg.fits`` (the sum of all bins) is not a bin and is left out.
- **NeXus/HDF5 file**: a 3-D histogram dataset (bins along one axis, detector rows
  and columns along the others) and a 1-D dataset of its time-of-flight bin centres
  (one per bin) or edges (one more) with a ``units`` attribute. By default the NeXus
  ``default``/``signal``/``axes`` attributes find both; options name them instead.

Every bin's times are turned into bin edges (:func:`edges_from_centres` for centres).
Images are ``(row, column)``; reads return float64 rows of one bin.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from .._errors import FwdfitError

FITS_SUFFIXES = (".fits", ".fit", ".fts")
HDF5_SUFFIXES = (".h5", ".hdf5", ".hdf", ".nxs", ".nx5", ".nexus")
SPECTRA_SUFFIX = "_Spectra.txt"
SUMMED_SUFFIX = "_SummedImg"  # MCP software: the sum over all bins, not a bin
# Seconds per unit of a time-of-flight ``units`` attribute (NeXus NX_TIME_OF_FLIGHT).
TIME_UNITS_S = {"s": 1.0, "second": 1.0, "seconds": 1.0, "sec": 1.0,
                "ms": 1e-3, "millisecond": 1e-3, "milliseconds": 1e-3,
                "us": 1e-6, "µs": 1e-6, "μs": 1e-6, "microsecond": 1e-6, "microseconds": 1e-6,
                "ns": 1e-9, "nanosecond": 1e-9, "nanoseconds": 1e-9}
TOF_AXIS_NAMES = ("time_of_flight", "tof", "frame_time")


@dataclasses.dataclass(frozen=True)
class TofStack:
    """One stack of per-bin images, opened for reading.

    Attributes:
        source: the file or folder, for messages.
        tof_edges_s: ``(n_bins + 1,)`` increasing bin edges, seconds as recorded.
        shape: ``(n_rows, n_cols)`` of every image.
        read_rows: ``(bin, start, stop) -> (stop - start, n_cols)`` float64 values of
            rows ``start:stop`` of bin ``bin``.
        integer_valued: whether the stored values are integers (counts).
    """

    source: str
    tof_edges_s: np.ndarray
    shape: tuple[int, int]
    read_rows: Callable[[int, int, int], np.ndarray]
    integer_valued: bool

    @property
    def n_bins(self) -> int:
        return len(self.tof_edges_s) - 1


def _first_line(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__


def _import_extra(module: str, what: str):
    """Import an optional reader, or a one-line error naming the extra to install."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise FwdfitError(f"reading {what} needs {module.split('.')[0]}: "
                          "pip install 'fwdfit[tof]'") from None


def edges_from_centres(centres: np.ndarray) -> np.ndarray:
    """Bin edges half-way between ``(n,)`` increasing centres; the outer edges half a
    neighbouring spacing out (one bin: FwdfitError, its width is unknown)."""
    if len(centres) < 2:
        raise FwdfitError("one time-of-flight bin: its width is unknown (give edges)")
    middle = 0.5 * (centres[1:] + centres[:-1])
    return np.concatenate([[centres[0] - (middle[0] - centres[0])], middle,
                           [centres[-1] + (centres[-1] - middle[-1])]])


def _check_times(times_s: np.ndarray, where: str) -> None:
    if times_s.size == 0 or not np.all(np.isfinite(times_s)):
        raise FwdfitError(f"{where}: time-of-flight values missing, NaN or infinite")
    if np.any(np.diff(times_s) <= 0):
        index = int(np.argmax(np.diff(times_s) <= 0))
        raise FwdfitError(f"{where}: times of flight do not increase (row {index + 1} to "
                          f"{index + 2}: {times_s[index]:g} s, {times_s[index + 1]:g} s)")


# ------------------------------------------------------------------------------ FITS


def read_spectra_times(path: Path) -> np.ndarray:
    """First column of an MCP ``*_Spectra.txt``: ``(n_bins,)`` times of flight, s."""
    try:
        table = np.loadtxt(path, ndmin=2)  # whitespace: tabs or spaces, CRLF or LF
    except (OSError, ValueError) as error:
        raise FwdfitError(f"cannot read spectra file {path}: {_first_line(error)}") from None
    times = table[:, 0] if table.size else np.empty(0)
    _check_times(times, f"spectra file {path}")
    return times


def _natural_key(path: Path) -> list:
    """Sort key that orders ``run_9`` before ``run_10``."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


def _frame_files(folder: Path) -> list[Path]:
    """The folder's per-bin FITS files in bin order; FwdfitError if numbers are skipped."""
    files = sorted((p for p in folder.iterdir() if p.is_file()
                    and p.suffix.lower() in FITS_SUFFIXES and not p.stem.endswith(SUMMED_SUFFIX)),
                   key=_natural_key)
    if not files:
        raise FwdfitError(f"no FITS files ({', '.join(FITS_SUFFIXES)}) in folder {folder}")
    numbers = [re.search(r"(\d+)$", p.stem) for p in files]
    if all(numbers):
        values = [int(m.group(1)) for m in numbers]
        gaps = [(a, b) for a, b in zip(values, values[1:]) if b != a + 1]
        if gaps:
            a, b = gaps[0]
            raise FwdfitError(f"{folder}: FITS frames missing or repeated: number {a} is "
                              f"followed by {b} ({len(gaps)} gap(s))")
    return files


def _spectra_file(folder: Path) -> Path:
    found = sorted(folder.glob(f"*{SPECTRA_SUFFIX}"))
    if len(found) != 1:
        state = "no" if not found else f"{len(found)}"
        raise FwdfitError(f"{folder}: {state} *{SPECTRA_SUFFIX} files (bin times); need one")
    return found[0]


def _fits_image(fits, path: Path, data: bool):
    """The first 2-D image HDU of a FITS file: its shape, or its data (float64)."""
    try:
        with fits.open(path, memmap=False) as hdus:
            for hdu in hdus:
                if getattr(hdu, "is_image", False) and hdu.header.get("NAXIS", 0) == 2:
                    if not data:
                        return tuple(int(n) for n in hdu.shape), hdu.header.get("BITPIX", -64) > 0
                    return np.asarray(hdu.data, dtype=np.float64)
    except Exception as error:  # astropy raises OSError, ValueError, TypeError, ...
        raise FwdfitError(f"cannot read FITS file {path}: {_first_line(error)}") from None
    raise FwdfitError(f"FITS file {path} holds no 2-D image")


def open_fits_folder(folder: Path) -> TofStack:
    """A folder of per-bin FITS images with its ``*_Spectra.txt`` (headers read here)."""
    fits = _import_extra("astropy.io.fits", "FITS")
    files = _frame_files(folder)
    spectra = _spectra_file(folder)
    times = read_spectra_times(spectra)
    if len(times) != len(files):
        raise FwdfitError(f"{spectra} has {len(times)} bin times but {folder} holds "
                          f"{len(files)} FITS frames")
    layouts = [_fits_image(fits, path, data=False) for path in files]
    shape = layouts[0][0]
    for path, (other, _) in zip(files, layouts):
        if other != shape:
            raise FwdfitError(f"FITS frames differ in shape: {path} is {other[0]}x{other[1]}, "
                              f"{files[0]} is {shape[0]}x{shape[1]}")

    def read_rows(index: int, start: int, stop: int) -> np.ndarray:
        return _fits_image(fits, files[index], data=True)[start:stop]

    return TofStack(source=str(folder), tof_edges_s=edges_from_centres(times),
                    shape=shape, read_rows=read_rows,
                    integer_valued=all(layout[1] for layout in layouts))


# ---------------------------------------------------------------------------- HDF5


def _text(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def _nexus_signal(h5, handle) -> str:
    """Path of the NeXus default plottable dataset (``default`` chain, else the first
    NXdata group with a ``signal``)."""
    group = handle
    while "default" in group.attrs and _text(group.attrs["default"]) in group:
        group = group[_text(group.attrs["default"])]
    if isinstance(group, h5.Group) and "signal" in group.attrs:
        return f"{group.name.rstrip('/')}/{_text(group.attrs['signal'])}"
    found: list[str] = []

    def visit(name, item):
        if (not found and isinstance(item, h5.Group) and "signal" in item.attrs
                and _text(item.attrs.get("NX_class", "NXdata")) == "NXdata"):
            found.append(f"/{name}/{_text(item.attrs['signal'])}")

    handle.visititems(visit)
    if not found:
        raise FwdfitError(f"{handle.filename}: no NeXus NXdata group with a signal; "
                          "name the histogram with --dataset")
    return found[0]


def _axis_names(data) -> list[str]:
    """NeXus ``axes`` of the data's group (one name per dimension, '.' for none)."""
    axes = data.parent.attrs.get("axes", data.attrs.get("axes"))
    if axes is None:
        return []
    if isinstance(axes, (str, bytes)):
        return [name.strip() for name in _text(axes).replace(":", ",").split(",")]
    return [_text(name) for name in axes]


def _tof_axis(h5, data, tof_dataset: str | None) -> tuple[object, int]:
    """The time-of-flight dataset and the data axis it labels."""
    handle = data.file
    names = _axis_names(data)
    if tof_dataset is None:
        candidates = [n for n in names if n in TOF_AXIS_NAMES and n in data.parent]
        candidates += [n for n in TOF_AXIS_NAMES if n in data.parent and n not in candidates]
        if not candidates:
            raise FwdfitError(f"{handle.filename}: no time-of-flight axis beside {data.name} "
                              f"(looked for {', '.join(TOF_AXIS_NAMES)}); name it with "
                              "--tof-dataset")
        tof = data.parent[candidates[0]]
    else:
        if tof_dataset not in handle or not isinstance(handle[tof_dataset], h5.Dataset):
            raise FwdfitError(f"{handle.filename}: no dataset {tof_dataset} (--tof-dataset)")
        tof = handle[tof_dataset]
    short = tof.name.rsplit("/", 1)[-1]
    if short in names:
        return tof, names.index(short)
    n_times = tof.size
    lengths = [axis for axis, n in enumerate(data.shape) if n in (n_times, n_times - 1)]
    if not lengths:
        raise FwdfitError(f"{handle.filename}: {tof.name} has {tof.shape} values, matching no "
                          f"axis of {data.name} {data.shape}")
    return tof, lengths[0]


def _tof_edges(tof, n_bins: int, where: str) -> np.ndarray:
    """Bin edges in seconds from a centres (n) or edges (n + 1) dataset with units."""
    units = _text(tof.attrs.get("units", "")).strip()
    if units not in TIME_UNITS_S:
        raise FwdfitError(f"{where}: {tof.name} has units {units!r}, not a time unit "
                          f"({', '.join(sorted(TIME_UNITS_S))})")
    values = np.asarray(tof[()], dtype=np.float64).ravel() * TIME_UNITS_S[units]
    _check_times(values, f"{where}: {tof.name}")
    if len(values) == n_bins + 1:
        return values
    if len(values) == n_bins:
        return edges_from_centres(values)
    raise FwdfitError(f"{where}: {tof.name} has {len(values)} times for {n_bins} bins "
                      "(need one per bin, or one more as edges)")


@contextmanager
def open_hdf5(path: Path, dataset: str | None = None,
              tof_dataset: str | None = None) -> Iterator[TofStack]:
    """A 3-D time-of-flight histogram in an HDF5/NeXus file, open while in the context."""
    h5 = _import_extra("h5py", "HDF5")
    try:
        handle = h5.File(path, "r")
    except Exception as error:  # OSError for a non-HDF5 file, and others
        raise FwdfitError(f"cannot read HDF5 file {path}: {_first_line(error)}") from None
    with handle:
        name = _nexus_signal(h5, handle) if dataset is None else dataset
        if name not in handle or not isinstance(handle[name], h5.Dataset):
            option = "" if dataset is None else " (--dataset)"
            raise FwdfitError(f"{path}: no dataset {name}{option}")
        data = handle[name]
        if data.ndim != 3:
            raise FwdfitError(f"{path}: {name} has shape {data.shape}, not (bins, rows, columns)")
        tof, axis = _tof_axis(h5, data, tof_dataset)
        edges = _tof_edges(tof, data.shape[axis], str(path))
        image_axes = [a for a in range(3) if a != axis]

        def read_rows(index: int, start: int, stop: int) -> np.ndarray:
            selection = [slice(None)] * 3
            selection[axis] = index
            selection[image_axes[0]] = slice(start, stop)
            try:
                return np.asarray(data[tuple(selection)], dtype=np.float64)
            except Exception as error:
                raise FwdfitError(f"cannot read bin {index} of {path}:{name}: "
                                  f"{_first_line(error)}") from None

        yield TofStack(source=f"{path}:{name}", tof_edges_s=edges,
                       shape=tuple(int(data.shape[a]) for a in image_axes), read_rows=read_rows,
                       integer_valued=np.issubdtype(data.dtype, np.integer))


@contextmanager
def open_tof_stack(spec: str, dataset: str | None = None,
                   tof_dataset: str | None = None) -> Iterator[TofStack]:
    """A FITS folder or an HDF5/NeXus file (by its suffix), open while in the context."""
    path = Path(spec).expanduser()
    if path.is_dir():
        if dataset is not None or tof_dataset is not None:
            raise FwdfitError(f"--dataset and --tof-dataset apply to HDF5 files, not the FITS "
                              f"folder {path}")
        yield open_fits_folder(path)
    elif path.is_file() and path.suffix.lower() in HDF5_SUFFIXES:
        with open_hdf5(path, dataset, tof_dataset) as stack:
            yield stack
    elif path.is_file():
        raise FwdfitError(f"{path}: a time-of-flight stack is a folder of FITS files or an "
                          f"HDF5/NeXus file ({', '.join(HDF5_SUFFIXES)})")
    else:
        raise FwdfitError(f"no such file or folder: {path}")


def check_same_bins(stacks: dict[str, TofStack]) -> None:
    """FwdfitError unless all stacks share the bins (edges within 1e-6 relative) and shape."""
    (first_name, first), *others = stacks.items()
    for name, stack in others:
        if stack.shape != first.shape:
            raise FwdfitError(f"{first_name} and {name} images differ in shape: "
                              f"{first.shape[0]}x{first.shape[1]} ({first.source}), "
                              f"{stack.shape[0]}x{stack.shape[1]} ({stack.source})")
        if stack.n_bins != first.n_bins:
            raise FwdfitError(f"{first_name} has {first.n_bins} time bins ({first.source}), "
                              f"{name} {stack.n_bins} ({stack.source})")
        scale = float(np.max(np.abs(first.tof_edges_s)))
        if not np.allclose(stack.tof_edges_s, first.tof_edges_s, rtol=0, atol=1e-6 * scale):
            index = int(np.argmax(np.abs(stack.tof_edges_s - first.tof_edges_s)))
            raise FwdfitError(f"{first_name} and {name} bins differ in time of flight (edge "
                              f"{index}: {first.tof_edges_s[index]:g} s, "
                              f"{stack.tof_edges_s[index]:g} s)")

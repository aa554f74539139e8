"""CSV tables with a header row: reading with validation, writing atomically."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from ._errors import FwdfitError


def read_columns(
    path: Path, required: Sequence[str], optional: Sequence[str] = ()
) -> dict[str, np.ndarray]:
    """Read named float columns of a CSV file (header row); every value finite, >= 2 rows."""
    try:
        with open(path, encoding="utf-8") as stream:
            header = [name.strip() for name in stream.readline().strip().split(",")]
            rows = np.loadtxt(stream, delimiter=",", ndmin=2)
    except FileNotFoundError:
        raise FwdfitError(f"{path}: file not found") from None
    except ValueError as error:
        raise FwdfitError(f"{path}: not a numeric CSV table ({error})") from None
    missing = [name for name in required if name not in header]
    if missing:
        raise FwdfitError(f"{path}: missing column(s) {', '.join(missing)} (has {', '.join(header)})")
    if rows.shape[0] < 2:
        raise FwdfitError(f"{path}: needs at least two rows of data")
    if rows.shape[1] != len(header):
        raise FwdfitError(f"{path}: {rows.shape[1]} values per row but {len(header)} column names")
    columns = {}
    for name in [*required, *(n for n in optional if n in header)]:
        values = rows[:, header.index(name)]
        if not np.all(np.isfinite(values)):
            raise FwdfitError(f"{path}: column {name} holds NaN or infinite values")
        columns[name] = values
    return columns


def write_columns(path: Path, columns: Mapping[str, np.ndarray]) -> None:
    """Write equal-length columns as a CSV with a header row (temp file, then rename)."""
    names = list(columns)
    data = np.column_stack([np.asarray(columns[n], dtype=float) for n in names])
    path = Path(path)
    handle, temp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(handle, "w", encoding="utf-8") as stream:
        np.savetxt(stream, data, delimiter=",", header=",".join(names), comments="", fmt="%.9g")
    os.replace(temp, path)

"""Files: CSV tables (read with validation, written atomically), output paths checked
before any work, and staged writes that leave nothing behind on failure or Ctrl-C.

Written files get the permissions a plain ``open`` gives (0666 less the umask).
"""

from __future__ import annotations

import os
import secrets
import shutil
import tempfile
import warnings
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from ._errors import FwdfitError


def read_columns(
    path: Path, required: Sequence[str], optional: Sequence[str] = ()
) -> dict[str, np.ndarray]:
    """Read named float columns of a CSV file (header row); every value finite, >= 2 rows."""
    try:
        with open(path, encoding="utf-8") as stream, warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "input contained no data": refused below
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


def check_finite(columns: Mapping[str, np.ndarray], where: str) -> None:
    """FwdfitError naming ``where`` and the first column that holds NaN or infinite values.

    Inside the validity domain (docs/SCENE.md) every result is finite, so this is a bug
    to report, but never a file of NaN.
    """
    for name, values in columns.items():
        bad = np.count_nonzero(~np.isfinite(np.asarray(values, dtype=float)))
        if bad:
            raise FwdfitError(f"{where}: {name} is NaN or infinite at {bad} of {np.size(values)} "
                              "points; nothing written (please report this scene)")


def write_columns(path: Path, columns: Mapping[str, np.ndarray], allow_nan: bool = False) -> None:
    """Write equal-length finite columns as a CSV with a header row (temp file, then rename).

    allow_nan: NaN stands for "no value" (e.g. a row that was not fitted) and is written as nan.
    """
    path = Path(path)
    if not allow_nan:
        check_finite(columns, str(path.name))
    names = list(columns)
    data = np.column_stack([np.asarray(columns[n], dtype=float) for n in names])
    with temporary_path(path) as temp:
        with open(temp, "x", encoding="utf-8") as stream:
            np.savetxt(stream, data, delimiter=",", header=",".join(names), comments="", fmt="%.9g")
        os.replace(temp, path)


@contextmanager
def temporary_path(path: Path) -> Iterator[Path]:
    """A fresh hidden name beside ``path`` to write to and rename; removed if still there."""
    temp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    try:
        yield temp
    finally:
        temp.unlink(missing_ok=True)


@contextmanager
def staged_folder(out_dir: Path) -> Iterator[Path]:
    """A hidden temporary folder beside ``out_dir``; its files move into ``out_dir`` at the end.

    On an error or Ctrl-C the temporary folder is removed and ``out_dir`` is neither
    created nor changed; files already in ``out_dir`` with other names stay.
    """
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".tmp", dir=out_dir.parent))
    try:
        yield staging
        out_dir.mkdir(exist_ok=True)
        for item in sorted(staging.iterdir()):
            os.replace(item, out_dir / item.name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def check_paths(inputs: Sequence[str | os.PathLike] = (), out_dir: str | os.PathLike | None = None,
                out_file: str | os.PathLike | None = None) -> None:
    """Refuse, before any work, missing input files and outputs that cannot be written.

    inputs: files that must exist. out_dir: a folder to write into (absent or a folder).
    out_file: a file to write (absent or a file). The nearest existing folder above the
    output and an existing output folder must accept new entries (checked by making and
    removing a temporary folder, which works for every user, root included).
    """
    for name in inputs:
        if not Path(name).is_file():
            state = "is not a file" if Path(name).exists() else "file not found"
            raise FwdfitError(f"{name}: {state}")
    for out, kind in ((out_dir, "folder"), (out_file, "file")):
        if out is None:
            continue
        out = Path(out)
        if out.exists() and (out.is_dir() != (kind == "folder")):
            other = "a folder" if out.is_dir() else "an existing file"
            raise FwdfitError(f"--out {out}: is {other}, not a {kind}")
        above = next(p for p in out.absolute().parents if p.exists())
        if not above.is_dir():
            raise FwdfitError(f"--out {out}: {above} is a file, not a folder")
        for folder in (above, out) if out.is_dir() else (above,):
            try:
                os.rmdir(tempfile.mkdtemp(prefix=".fwdfit-check-", dir=folder))
            except OSError as error:
                raise FwdfitError(f"--out {out}: cannot write in {folder} "
                                  f"({error.strerror})") from None

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
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from .._errors import FwdfitError
from .._interrupt import interrupts_deferred, removed_on_interrupt


def read_columns(
    path: Path, required: Sequence[str], optional: Sequence[str] = (), passive: Sequence[str] | None = None
) -> dict[str, np.ndarray]:
    """Read named float columns of a CSV file (header row); every value finite, >= 2 rows.

    passive: columns that may be present and are not read; when given, any other column
    is an error (a misspelt ``T_error`` is not silently ignored).
    """
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
    if passive is not None:
        unknown = [name for name in header if name not in {*required, *optional, *passive}]
        if unknown:
            raise FwdfitError(f"{path}: unknown column {unknown[0]} (read: {', '.join([*required, *optional])}; "
                              f"allowed besides: {', '.join(passive)})")
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
        with removed_on_interrupt(temp):
            yield temp
    finally:
        temp.unlink(missing_ok=True)


OUTPUT_MARKER = ".fwdfit-output"  # in every folder fwdfit writes: a later run may replace that folder


def is_fwdfit_output(folder: Path) -> bool:
    """True if ``folder`` holds fwdfit's marker (a folder an earlier fwdfit command wrote)."""
    return (Path(folder) / OUTPUT_MARKER).is_file()


def mark_output(folder: Path) -> None:
    """Make ``folder`` (if absent) and mark it as fwdfit's output folder."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / OUTPUT_MARKER).write_text("written by fwdfit: a later run may replace this folder\n",
                                        encoding="utf-8")


@contextmanager
def staged_folder(out_dir: Path, add: bool = False) -> Iterator[Path]:
    """A hidden temporary folder beside ``out_dir`` that becomes ``out_dir`` at the end.

    ``out_dir`` is created, or replaces an empty folder or one an earlier fwdfit run wrote
    (its stale files go with it); ``add``: the new files join those of a folder fwdfit
    wrote (a posterior beside its fit). A non-empty folder that fwdfit did not write is
    refused. On an error or Ctrl-C the temporary folder is removed and ``out_dir`` is
    neither created nor changed.
    """
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".tmp", dir=out_dir.parent))
    try:
        with removed_on_interrupt(staging):
            yield staging
            mark_output(staging)
            with interrupts_deferred():
                _commit(staging, out_dir, add)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _commit(staging: Path, out_dir: Path, add: bool) -> None:
    """Put the staged folder's files in place (see ``staged_folder``)."""
    if out_dir.is_dir() and any(out_dir.iterdir()) and not is_fwdfit_output(out_dir):
        raise FwdfitError(f"--out {out_dir}: {_NOT_OURS}")
    if add and out_dir.is_dir():
        for item in sorted(staging.iterdir()):
            os.replace(item, out_dir / item.name)
        return
    if not out_dir.exists():
        os.rename(staging, out_dir)
        return
    old = out_dir.with_name(f".{out_dir.name}.{secrets.token_hex(4)}.old")
    os.rename(out_dir, old)
    os.rename(staging, out_dir)
    shutil.rmtree(old, ignore_errors=True)


_NOT_OURS = "holds files that fwdfit did not write; name a new or empty folder"


def check_paths(inputs: Sequence[str | os.PathLike] = (), out_dir: str | os.PathLike | None = None,
                out_file: str | os.PathLike | None = None) -> None:
    """Refuse, before any work, missing input files and outputs that cannot be written.

    inputs: files that must exist. out_dir: a folder to write into (absent or a folder).
    out_file: a file to write (absent or a file). The nearest existing folder above the
    output and an existing output folder must accept new entries (checked by making and
    removing a temporary folder, which works for every user, root included); an existing
    output folder must be empty or one that fwdfit wrote (``staged_folder``).
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
        if kind == "folder" and out.is_dir() and any(out.iterdir()) and not is_fwdfit_output(out):
            raise FwdfitError(f"--out {out}: {_NOT_OURS}")
        for folder in (above, out) if out.is_dir() else (above,):
            try:
                os.rmdir(tempfile.mkdtemp(prefix=".fwdfit-check-", dir=folder))
            except OSError as error:
                raise FwdfitError(f"--out {out}: cannot write in {folder} "
                                  f"({error.strerror})") from None


def refuse_inputs_in(out: str | os.PathLike, reads: Iterable[str | os.PathLike]) -> None:
    """Refuse an output ``out`` (a folder or a file) that is, or holds, a file the command reads."""
    out = Path(out).resolve()
    for name in reads:
        path = Path(name).resolve()
        if path == out or out in path.parents:
            where = "is" if path == out else "holds"
            raise FwdfitError(f"--out {name if path == out else out}: {where} an input "
                              f"({Path(name).name}); name another folder")

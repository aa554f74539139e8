"""Many images (a tomography or time series) fitted with one scene as template
(``fwdfit fit-images``): serially, or on a Dask distributed cluster, resumably.

Each image is fitted by ``fit_image`` with the scene's image replaced
(``_scene.with_image``) and written to DIR/<image stem>/ as ``fwdfit fit-image`` writes
it (staged, then moved in: a folder holding every output is complete). A run skips the
images whose folder is complete, so an interrupted run resumes where it stopped. Each
process compiles a geometry once (``_predict`` keeps its compiled programs), and the
persistent compilation cache (FWDFIT_CACHE_DIR) shares them between processes. Images
are read and outputs written by the workers: with ``--scheduler`` they need the same
paths (a shared file system). DIR/summary.csv has a line per image.
"""

from __future__ import annotations

import csv
import glob
import json
import os
import shutil
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

from .._errors import FwdfitError
from ..io._tables import mark_output, temporary_path

OUTPUT_FILES = ("T_att.tif", "T_corrected.tif", "residual.tif", "rows.csv", "result.json", "overview.png")
_TIFF_SUFFIXES = (".tif", ".tiff")
STATUS_OK, STATUS_REJECTED, STATUS_NOT_CONVERGED, STATUS_FAILED = "ok", "rejected", "not_converged", "failed"


def find_images(patterns: Sequence[str]) -> list[Path]:
    """The image files named by ``patterns`` (files, folders of .tif/.tiff, or globs), in
    the order given (a folder's or glob's matches sorted by name), each once."""
    found: list[Path] = []
    for pattern in patterns:
        path = Path(pattern)
        if path.is_dir():
            matches = sorted(p for p in path.iterdir() if p.suffix.lower() in _TIFF_SUFFIXES and p.is_file())
            if not matches:
                raise FwdfitError(f"{pattern}: no .tif or .tiff images in this folder")
        elif glob.has_magic(pattern):
            matches = sorted(Path(p) for p in glob.glob(pattern) if Path(p).is_file())
            if not matches:
                raise FwdfitError(f"{pattern}: no image matches")
        elif path.is_file():
            matches = [path]
        else:
            raise FwdfitError(f"{pattern}: {'is not a file' if path.exists() else 'file not found'}")
        found.extend(matches)
    images = list(dict.fromkeys(p.resolve() for p in found))
    stems: dict[str, Path] = {}
    for image in images:
        if image.stem in stems:
            raise FwdfitError(f"{image}: same name as {stems[image.stem]} (each image's output folder is "
                              "DIR/<name>): rename one")
        stems[image.stem] = image
    return images


def check_images(images: Sequence[Path], shape: tuple[int, int]) -> None:
    """Refuse, from the files' headers alone, an image that is not a 2-D float TIFF of ``shape``."""
    import numpy as np
    import tifffile

    for image in images:
        try:
            with tifffile.TiffFile(image) as tiff:
                series = tiff.series[0]
                found, dtype = tuple(d for d in series.shape if d != 1), np.dtype(series.dtype)
        except Exception as error:  # tifffile raises many types for a damaged or foreign file
            raise FwdfitError(f"{image}: not a readable TIFF image ({_first_line(error)})") from None
        if found != tuple(shape):
            raise FwdfitError(f"{image}: {' x '.join(map(str, found)) or 'no'} pixels, the template image "
                              f"{shape[0]} x {shape[1]}: every image must have the template's rows and columns")
        if not np.issubdtype(dtype, np.floating):
            raise FwdfitError(f"{image}: pixel type {dtype}: needs a float image of normalised transmission")


def _first_line(error: Exception) -> str:
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__


def is_complete(folder: Path) -> bool:
    """The folder holds every output of a fitted image."""
    return all((folder / name).is_file() for name in OUTPUT_FILES)


def _prepare_process(cache: bool) -> None:
    """float64, XLA's log off and (``cache``) the persistent compilation cache, in this process."""
    import jax

    from ..inference._cache import enable_compilation_cache

    jax.config.update("jax_enable_x64", True)
    try:
        jax.config.update("jax_logging_level", "CRITICAL")
    except AttributeError:  # an older jax: its log stays on
        pass
    if cache:
        enable_compilation_cache()


def fit_one(scene_path: str, image: str, folder: str, accuracy: float | None, cache: bool) -> dict:
    """Fit one image with the scene as template and write its outputs to ``folder``; the
    summary line of the image (``summary_line``). Runs in a worker (or the main process):
    a bad image is a line with status "failed" and its message, never an exception."""
    import warnings

    from ._image_fit import fit_image
    from ._image_output import write_image_fit
    from ..scene._scene import load_scene, with_image

    _prepare_process(cache)
    try:
        scene = with_image(load_scene(scene_path), image)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the fit's notes are in result.json
            write_image_fit(fit_image(scene, accuracy=accuracy), Path(folder))
    except Exception as error:  # one image's failure must not stop the series: it is reported
        return {"image": Path(image).name, "status": STATUS_FAILED, "resumed": 0, "message": _first_line(error)}
    return summary_line(Path(image), Path(folder), resumed=False)


def summary_line(image: Path, folder: Path, resumed: bool) -> dict:
    """An image's line of summary.csv from its result.json: status, chi-square, rows fitted
    and flagged, the shared parameters with their errors."""
    result = json.loads((folder / "result.json").read_text())
    status = (STATUS_NOT_CONVERGED if not result["converged"] else
              STATUS_OK if result["accepted"] else STATUS_REJECTED)
    line = {"image": image.name, "status": status, "resumed": int(resumed), "message": result["message"],
            "chi2_reduced": result["chi2_reduced"], "rows": result["rows"]["total"],
            "rows_fitted": result["rows"]["fitted"], "rows_flagged": result["rows"]["flagged"]}
    for name, value in result["parameters"].items():
        line[name], line[f"{name}_err"] = value["value"], value["error"]
    return line


def write_summary(lines: Sequence[dict], path: Path) -> None:
    """summary.csv: a line per image (columns: the union of the lines' keys, in order)."""
    columns = list(dict.fromkeys(key for line in lines for key in line))
    with temporary_path(path) as temp:
        with open(temp, "x", encoding="utf-8", newline="") as stream:
            writer = csv.DictWriter(stream, columns, restval="")
            writer.writeheader()
            for line in lines:
                writer.writerow({k: (f"{v:.9g}" if isinstance(v, float) else v) for k, v in line.items()})
        os.replace(temp, path)


def _remove_stale_staging(out_dir: Path, stems: Sequence[str]) -> None:
    """Staged folders (.<stem>.*.tmp) a killed run left behind, for the images to fit."""
    if out_dir.is_dir():
        for stem in stems:
            for stale in out_dir.glob(f".{glob.escape(stem)}.*.tmp"):
                shutil.rmtree(stale, ignore_errors=True)


def local_client(scheduler: str | None, workers: int):
    """A Dask client of the cluster at ``scheduler``, or of a new LocalCluster of ``workers``
    single-threaded processes; and the cluster to close (None for an existing one)."""
    try:
        import logging

        from distributed import Client, LocalCluster
    except ImportError:
        raise FwdfitError("a Dask cluster needs dask.distributed: pip install 'fwdfit[cluster]' "
                          "(or fit serially with --workers 1)") from None
    if scheduler is not None:
        try:
            return Client(scheduler, timeout="20s"), None
        except (OSError, TimeoutError, ValueError) as error:
            raise FwdfitError(f"--scheduler {scheduler}: cannot connect ({error})") from None
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                           silence_logs=logging.ERROR)
    return Client(cluster), cluster


def _run_dask(tasks: list[tuple], scheduler: str | None, workers: int) -> Iterator[tuple[int, dict]]:
    """(task index, summary line) of every task, as the cluster finishes them."""
    from distributed import as_completed

    client, cluster = local_client(scheduler, workers)
    try:
        futures = {client.submit(fit_one, *task, pure=False): i for i, task in enumerate(tasks)}
        for future in as_completed(futures):
            try:
                line = future.result()
            except Exception as error:  # the worker died (KilledWorker, ...): fit_one itself reports errors
                line = {"image": Path(tasks[futures[future]][1]).name, "status": STATUS_FAILED, "resumed": 0,
                        "message": f"{type(error).__name__}: {_first_line(error)}"}
            yield futures[future], line
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def fit_series(scene_path: str | Path, images: Sequence[Path], out_dir: str | Path, *,
               scheduler: str | None = None, workers: int = 1, accuracy: float | None = None,
               cache: bool = True, say: Callable[[str], None] | None = None) -> list[dict]:
    """Fit every image with the scene at ``scene_path`` as template into out_dir/<stem>/,
    skipping images already complete there; write out_dir/summary.csv. Serial in this
    process when ``workers`` is 1 and no ``scheduler`` is given, else on a Dask cluster.
    Returns the summary lines (in the images' order). say: progress lines (stderr)."""
    say = say or (lambda text: None)
    out_dir = Path(out_dir)
    lines: list[dict | None] = [None] * len(images)
    for i, image in enumerate(images):
        if is_complete(out_dir / image.stem):
            try:
                lines[i] = summary_line(image, out_dir / image.stem, resumed=True)
            except (OSError, ValueError, KeyError, TypeError):  # a damaged result.json: fitted again
                pass
    done = [i for i, line in enumerate(lines) if line is not None]
    todo = [i for i, line in enumerate(lines) if line is None]
    say(f"{len(images)} images: {len(done)} done before (skipped), {len(todo)} to fit"
        + ("" if not todo else " serially" if workers == 1 and scheduler is None
           else f" on {scheduler}" if scheduler else f" on {workers} local Dask workers"))
    mark_output(out_dir)  # a later run may resume in it (check_paths)
    _remove_stale_staging(out_dir, [images[i].stem for i in todo])
    tasks = [(str(scene_path), str(images[i]), str(out_dir / images[i].stem), accuracy, cache) for i in todo]
    if workers == 1 and scheduler is None:
        results = ((k, fit_one(*task)) for k, task in enumerate(tasks))
    else:
        results = _run_dask(tasks, scheduler, workers)
    begin = time.perf_counter()
    for count, (k, line) in enumerate(results, start=1):
        lines[todo[k]] = line
        rate = count / max(time.perf_counter() - begin, 1e-9)
        note = f": {line['message']}" if line["status"] == STATUS_FAILED else ""
        say(f"images {len(done) + count}/{len(images)}, {rate:.2f} images/s, "
            f"{(len(todo) - count) / rate:.0f} s left; {line['image']}: {line['status']}{note}")
    write_summary(lines, out_dir / "summary.csv")
    return lines


"""A user cache folder for compiled programs: the second fit of a geometry loads its
compiled model instead of compiling it again (``_predict`` keeps the model's programs
there; JAX's persistent compilation cache, switched on here, keeps the others).

``FWDFIT_CACHE_DIR`` names the folder (default: ``$XDG_CACHE_HOME/fwdfit``, else
``~/.cache/fwdfit``); ``FWDFIT_CACHE_DIR=off`` (or an empty value) turns the cache off.
The cache is keyed by the compiled program, so data, starts and values never go stale
in it; a changed fwdfit (version or source) or JAX version simply compiles anew.
"""

from __future__ import annotations

import os
from pathlib import Path

_MIN_COMPILE_TIME_S = 0.5  # programs compiled faster than this are not worth a file
_OFF = {"", "0", "off", "none", "false"}


def cache_dir() -> Path | None:
    """The cache folder from the environment, or None when the cache is switched off."""
    value = os.environ.get("FWDFIT_CACHE_DIR")
    if value is not None:
        return None if value.strip().lower() in _OFF else Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "fwdfit"


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path | None:
    """Keep compiled programs in ``path`` (default: ``cache_dir()``); returns the folder used.

    Returns None, changing nothing, when the cache is switched off or its folder cannot
    be created (a read-only home, say): fitting then simply compiles every time.
    """
    import jax

    folder = Path(path) if path is not None else cache_dir()
    if folder is None:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", _MIN_COMPILE_TIME_S)
    return folder

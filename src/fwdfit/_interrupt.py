"""Ctrl-C at any moment: one line, exit status 130, nothing written (standard library only).

Python runs a signal handler only between bytecodes of the main thread, so a SIGINT that
arrives while XLA compiles (C++, for seconds) would wait, and a ``KeyboardInterrupt``
raised inside JAX's callbacks is swallowed ("Exception ignored in ...") or unwinds a
half-built program (a segmentation fault at exit). So the command line does not raise:
the C-level handler writes the signal to a pipe (``signal.set_wakeup_fd``), a watcher
thread wakes at once, removes the files being written (``removed_on_interrupt``) and
ends the process with ``os._exit``. While an output folder is put in place
(``interrupts_deferred``) the exit waits until that is done, so outputs are whole or absent.
"""

from __future__ import annotations

import os
import shutil
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

EXIT_INTERRUPTED = 130  # 128 + SIGINT, as shells report it
_MESSAGE = b"fwdfit: interrupted\n"

_lock = threading.RLock()
_being_written: set[Path] = set()  # removed if the process is interrupted
_deferring = 0  # > 0: an output is being put in place; the exit waits
_pending = False
_installed = False


@contextmanager
def removed_on_interrupt(path: Path) -> Iterator[None]:
    """``path`` (a file or folder being written) is removed if Ctrl-C ends the process."""
    with _lock:
        _being_written.add(Path(path))
    try:
        yield
    finally:
        with _lock:
            _being_written.discard(Path(path))


@contextmanager
def interrupts_deferred() -> Iterator[None]:
    """An interrupt inside this block ends the process only once the block is done."""
    global _deferring
    with _lock:
        _deferring += 1
    try:
        yield
    finally:
        with _lock:
            _deferring -= 1
            if _pending and not _deferring:
                _exit_interrupted()


def _exit_interrupted() -> None:
    """Remove what is being written, say so in one line, end the process (status 130)."""
    global _pending
    with _lock:
        if _deferring:
            _pending = True
            return
        for path in _being_written:
            if path.is_dir():
                shutil.rmtree(path, ignore_errors=True)
            else:
                try:
                    path.unlink()
                except OSError:
                    pass
        os.write(2, _MESSAGE)
        os._exit(EXIT_INTERRUPTED)


def _watch(read_fd: int) -> None:
    while True:
        try:
            data = os.read(read_fd, 64)
        except InterruptedError:
            continue
        if not data:
            return
        if signal.SIGINT in data:
            _exit_interrupted()


def install_interrupt_handler() -> None:
    """Make Ctrl-C end this process at once, as the module docstring says (main thread only).

    Called by the command line before it imports JAX; a library caller keeps Python's
    ``KeyboardInterrupt``. Once per process; outside the main thread it does nothing.
    """
    global _installed
    if _installed or threading.current_thread() is not threading.main_thread():
        return
    _installed = True
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    signal.signal(signal.SIGINT, lambda signum, frame: _exit_interrupted())
    signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    threading.Thread(target=_watch, args=(read_fd,), name="fwdfit-interrupt", daemon=True).start()

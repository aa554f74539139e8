"""Progress lines on stderr, one convention for every command: ``[  3.2 s] what happens``.

Results and tables go to stdout; progress goes to stderr, so a user can redirect one
without the other, and ``--quiet`` silences it.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

_TICK_S = 5.0  # a "still ..." line this often during a long silent stage (compiling)


class Progress:
    """Says what happens, with the seconds since it was made; silent if not ``enabled``."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.begin = time.perf_counter()

    def __call__(self, text: str) -> None:
        if self.enabled:
            print(f"[{time.perf_counter() - self.begin:6.1f} s] {text}", file=sys.stderr, flush=True)

    @contextmanager
    def ticking(self, doing: str) -> Iterator[None]:
        """A "still <doing>" line every few seconds until the block ends (JAX compiling)."""
        done = threading.Event()
        start = time.perf_counter()

        def tick():
            while not done.wait(_TICK_S):
                self(f"still {doing} ({time.perf_counter() - start:.0f} s)")

        thread = threading.Thread(target=tick, daemon=True) if self.enabled else None
        if thread is not None:
            thread.start()
        try:
            yield
        finally:
            done.set()


def as_progress(progress: bool | Progress) -> Progress:
    """A ``Progress`` from a library argument (True, False, or one to share)."""
    return progress if isinstance(progress, Progress) else Progress(bool(progress))

"""The ``fwdfit`` command (``main``, the console entry point ``fwdfit.cli:main``), a thin
shell over the library. Importing it imports only the standard library: each command
imports what it runs when it runs."""

from ._main import EXIT_NOT_CONVERGED as EXIT_NOT_CONVERGED
from ._main import EXIT_REJECTED as EXIT_REJECTED
from ._main import build_parser as build_parser
from ._main import main as main

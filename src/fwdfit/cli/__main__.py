"""``python -m fwdfit.cli``: the ``fwdfit`` command."""

import sys

from ._main import main

sys.exit(main())

"""``python -m fwdfit``: the ``fwdfit`` command."""

import sys

from .cli import main

sys.exit(main())

"""``python -m treeinfer``: the same command line as the ``treeinfer`` script."""

import sys

from .cli import main

sys.exit(main())

"""``python -m shape_detector ...`` is the ``shape-detector`` command."""

import sys

from .cli import main

sys.exit(main())

"""``python -m egorefine.cli``: the ``egorefine`` command."""

import sys

from . import main

sys.exit(main())

"""``python -m app.cli``: the ``invisible-map`` command."""

import sys

from app.cli import main

sys.exit(main())

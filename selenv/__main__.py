"""``python -m selenv``: the ``selenv`` command line (see :mod:`selenv.cli`)."""

from __future__ import annotations

import sys

from selenv.cli import main

sys.exit(main())

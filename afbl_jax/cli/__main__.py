"""``python -m afbl_jax.cli ...``: the ``afbl`` command."""

import sys

from . import main

sys.exit(main())

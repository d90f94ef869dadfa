"""`python -m sqjax.cli ...`: the same as `python -m sqjax ...`."""

import sys

from . import main

sys.exit(main())

"""`python -m sqjax ...`: the command line of `sqjax.cli`."""

import sys

from .cli import main

sys.exit(main())

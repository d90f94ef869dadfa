"""`python -m sqjax.cli ...`: the same as `python -m sqjax ...`."""

from . import console

console()

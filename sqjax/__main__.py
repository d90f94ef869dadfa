"""`python -m sqjax ...`: the command line of `sqjax.cli`."""

from .cli import console

console()

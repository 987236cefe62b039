"""``python -m forestreg.cli``."""

from . import entry

entry()

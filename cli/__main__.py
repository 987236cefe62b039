"""``python -m forestreg.cli``."""

import sys

from . import main

sys.exit(main())

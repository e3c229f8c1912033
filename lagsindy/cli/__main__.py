"""``python -m lagsindy.cli``: the same as ``python -m lagsindy``."""

import sys

from . import main

sys.exit(main())

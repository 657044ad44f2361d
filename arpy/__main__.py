"""Allow ``python -m arpy ...``."""

import sys

from .cli import main

sys.exit(main())

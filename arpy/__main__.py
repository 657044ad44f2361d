"""Allow ``python -m arpy ...``."""

from .cli import main

raise SystemExit(main())

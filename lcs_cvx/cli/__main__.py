"""``python -m lcs_cvx.cli``."""

from . import main

raise SystemExit(main())

"""``python -m logger.cli``: the same entry point as the installed ``logger`` command."""

import sys

from logger.cli import main

sys.exit(main())

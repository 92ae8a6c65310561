"""`python -m sgjax_cli ...`: the same as the `sgjax` command."""

import sys

from sgjax_cli import main

sys.exit(main())

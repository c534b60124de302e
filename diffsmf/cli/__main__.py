"""``python -m diffsmf.cli`` is the ``diffsmf`` command (`diffsmf.cli.main`)."""

import sys

from diffsmf.cli import main

sys.exit(main())

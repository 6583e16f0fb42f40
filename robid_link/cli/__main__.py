"""``python -m robid_link.cli``: the ``robid`` command."""

import sys

from robid_link.cli import main

sys.exit(main())

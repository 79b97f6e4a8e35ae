"""``python -m agos.deploy.cli ...``: the ``agos`` command (how the local launcher starts its children)."""

import sys

from agos.deploy.cli import main

sys.exit(main())

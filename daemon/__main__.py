"""``python -m daemon`` is the ``mocapd`` command."""

import sys

from daemon.cli import main

sys.exit(main())

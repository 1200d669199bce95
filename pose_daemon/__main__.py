"""``python -m pose_daemon`` = the ``pose-daemon`` command."""

import sys

from .cli import main

sys.exit(main())

"""``python -m wardmap.cli`` runs the console script."""

import sys

from wardmap.cli.main import main

sys.exit(main())

"""`python -m genreg_ros.replay`: the genreg-replay command."""

import sys

from genreg_ros.replay.cli import main

sys.exit(main())

"""``python -m aocontrol``: the command line."""

import sys

from aocontrol.study.cli import main

sys.exit(main())

"""`python -m bitcomm ...`: the `bitcomm` command, for an environment whose scripts folder is not on PATH."""

import sys

from bitcomm.cli import main

sys.exit(main())

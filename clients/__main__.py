"""``python -m clients`` = ``shadowcorr-client``."""

import sys

from .cli import main

sys.exit(main())

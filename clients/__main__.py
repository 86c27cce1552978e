"""``python -m shadowcorr_client`` = ``shadowcorr-client``."""

import sys

from .cli import main

sys.exit(main())

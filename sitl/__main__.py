"""``python -m sitl run ...`` is the same as the ``sitl`` console script."""

import sys

from sitl.cli import main

sys.exit(main())

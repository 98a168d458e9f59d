"""``python -m datagen CONFIG ...``: see :mod:`datagen.generate`."""

import sys

from .generate import main

sys.exit(main())

"""``python -m bsms.pretrained RUN_DIR OUT`` (or ``RUN RUN ... OUT``, an ensemble): the export of
trained runs as pretrained folders, :mod:`bsms.infer.pretrained`, run as a command."""

import sys

from bsms.infer.pretrained import main

if __name__ == "__main__":
    sys.exit(main())

"""``python -m bsms.evaluate RUN_DIR [--compare RUN ...]``: :func:`bsms.evaluate.main`."""

from bsms.evaluate import main

raise SystemExit(main())

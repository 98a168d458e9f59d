"""``python -m bsms.infer RUN_DIR --mesh FILE [...]``: :func:`bsms.infer.main`."""

from bsms.infer import main

raise SystemExit(main())

"""``python -m tar_rl`` is the ``tar-rl`` command."""

from tar_rl.cli import main

raise SystemExit(main())

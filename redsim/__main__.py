"""``python -m redsim``: the same command line as the ``redsim`` script."""

from redsim.cli import main

raise SystemExit(main())

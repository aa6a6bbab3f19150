"""``python -m latentdrive``: the same command line as the ``latentdrive`` console script."""

from latentdrive.cli import main

raise SystemExit(main())

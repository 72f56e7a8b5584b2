"""``python -m esa_client.compare``: the same as the ``esa-compare`` command."""

from esa_client.compare.cli import main

raise SystemExit(main())

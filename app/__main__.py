"""Allow ``python -m app`` as an alias of the ``floornav`` command."""

from app.cli import main

raise SystemExit(main())

"""``python -m canical`` runs the command-line interface."""

from canical.cli import main

raise SystemExit(main())

"""``python -m canical`` runs the command-line interface."""

from canical.commands.cli import main

raise SystemExit(main())

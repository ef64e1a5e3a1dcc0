"""One module per ``canical`` command; each exposes ``register(subparsers)``."""

from canical.commands import apply, calibrate, demo

COMMANDS = (calibrate, apply, demo)

"""One module per ``canical`` command; each exposes ``register(subparsers)``."""

from canical.commands import apply, calibrate, demo, emulate, pull, push, record, serve

COMMANDS = (calibrate, apply, demo, serve, record, emulate, push, pull)

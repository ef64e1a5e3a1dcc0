"""One module per ``canical`` command; each exposes ``register(subparsers)``."""

from canical.commands import apply, calibrate, demo, emulate, pull, push, serve

COMMANDS = (calibrate, apply, demo, serve, emulate, push, pull)

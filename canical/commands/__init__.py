"""One module per ``canical`` command; each exposes ``register(subparsers)``."""

from canical.commands import apply, calibrate, demo, emulate, pull, push

COMMANDS = (calibrate, apply, demo, emulate, push, pull)

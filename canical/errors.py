"""The one exception type a user sees.

Anything the user can fix (a bad file, a missing column, a set for another
sensor) is raised as :class:`CanicalError`; the CLI prints its message as one
line and exits with status 2. Every other exception is a bug and keeps its
traceback.
"""


class CanicalError(Exception):
    """A problem with the user's input, stated in one actionable line."""

    exit_status = 2

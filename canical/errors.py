"""The one exception type a user sees.

Anything the user can fix (a bad file, a missing column, a set for another
sensor) is raised as :class:`CanicalError`; the CLI prints its message as one
line and exits with status 2. Every other exception is a bug and keeps its
traceback.
"""


#: The longest refusal a user is shown: a message that echoes a user's value (a YAML alias bomb
#: echoed 3.5 million characters) is cut here, and its line breaks folded.
MAX_MESSAGE_CHARS = 400


class CanicalError(Exception):
    """A problem with the user's input, stated in one actionable line."""

    exit_status = 2

    def __str__(self) -> str:
        return one_line(super().__str__())


def one_line(text: str, limit: int = MAX_MESSAGE_CHARS) -> str:
    """``text`` on one line (line breaks and runs of blanks folded to a space), cut to ``limit``."""
    folded = " ".join(text.split())
    return folded if len(folded) <= limit else folded[: limit - 1] + "…"

"""Small helpers the tests share for writing simulated sessions to disk."""

from pathlib import Path

from canical.sessions.csv_file import format_session
from canical.sessions.session import Session


def write_session(path: Path, session: Session) -> Path:
    path.write_text(format_session(session))
    return path

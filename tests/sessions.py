"""Small helpers the tests share for writing simulated sessions to disk."""

from pathlib import Path

from canical.session import Session
from canical.session_csv import format_session


def write_session(path: Path, session: Session) -> Path:
    path.write_text(format_session(session))
    return path

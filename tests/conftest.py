"""Shared pytest configuration for the canical test suite.

Tests mirror the package's rings (``tests/calibrate/``, ``tests/bus/``, …); everything they
share lives in ``tests/support/``: fixtures, session writers, the vcan and systemd guests.
The vcan machinery (``@pytest.mark.vcan`` tests on a real SocketCAN bus, through a User-mode
Linux guest when the host kernel lacks SocketCAN; fixtures ``vcan_channel``/``vcan_channels``)
is a plugin module there.
"""

import signal
from collections.abc import Iterator

import pytest

# tests/ is a rootless dir on sys.path (pytest's default "prepend" import mode), so the
# support package is importable as "support"; as "tests.support" should tests/ become a package.
pytest_plugins = [f"{__package__}.support.vcan_plugin" if __package__ else "support.vcan_plugin"]

#: Signals whose handlers the code under test installs (serve, record, emulate): a test must leave
#: them as it found them, or a later test that relies on them fails in the full run only.
WATCHED_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


@pytest.fixture(autouse=True)
def _signal_handlers_left_as_found() -> Iterator[None]:
    """Fail the test that leaves a signal's handler changed (and put the handler back for the next)."""
    before = {s: signal.getsignal(s) for s in WATCHED_SIGNALS}
    yield
    changed = [s for s in WATCHED_SIGNALS if signal.getsignal(s) is not before[s]]
    for s in changed:
        signal.signal(s, before[s])
    names = ", ".join(signal.Signals(s).name for s in changed)
    assert not changed, f"the test left the handler of {names} changed"

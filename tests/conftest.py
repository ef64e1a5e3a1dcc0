"""Shared pytest configuration for the canical test suite.

Tests mirror the package's rings (``tests/calibrate/``, ``tests/bus/``, …); everything they
share lives in ``tests/support/``: fixtures, session writers, the vcan and systemd guests.
The vcan machinery (``@pytest.mark.vcan`` tests on a real SocketCAN bus, through a User-mode
Linux guest when the host kernel lacks SocketCAN; fixtures ``vcan_channel``/``vcan_channels``)
is a plugin module there.
"""

# tests/ is a rootless dir on sys.path (pytest's default "prepend" import mode), so the
# support package is importable as "support"; as "tests.support" should tests/ become a package.
pytest_plugins = [f"{__package__}.support.vcan_plugin" if __package__ else "support.vcan_plugin"]

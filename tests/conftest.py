"""Shared pytest configuration for the canical test suite.

The vcan machinery (``@pytest.mark.vcan`` tests on a real SocketCAN bus, through a User-mode
Linux guest when the host kernel lacks SocketCAN; fixtures ``vcan_channel``/``vcan_channels``)
lives in its own plugin module so this file stays free for ordinary shared fixtures.
"""

# Importable as "vcan_plugin" when tests/ is a rootless dir on sys.path (pytest's default
# "prepend" import mode), or as "tests.vcan_plugin" should tests/ ever become a package.
pytest_plugins = [f"{__package__}.vcan_plugin" if __package__ else "vcan_plugin"]

"""What the tests share: fixtures, session writers, and the vcan / systemd guest machinery.

Test modules import these as ``from support.X import …`` (tests/ is on sys.path).
"""

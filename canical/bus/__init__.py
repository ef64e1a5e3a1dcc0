"""The daemon on the vehicle: raw frames in, corrected frames out, in real time.

:mod:`.daemon` runs the frame path and the hot reload, :mod:`.daemon_config` reads its
configuration, :mod:`.active_sets` loads the sets from files or from the sensor,
:mod:`.sd_notify` talks to systemd, :mod:`.service_install` installs the units, and
:mod:`.recording` turns bus traffic into a session (the demo). Imports :mod:`canical.device`
and the rings below it.
"""

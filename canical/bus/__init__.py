"""The daemon on the vehicle: raw frames in, corrected frames out, in real time.

:mod:`.daemon` is the loop that ties the parts: :mod:`.socketcan` (the raw socket, with
:mod:`.socketcan_constants` for what python-can's constants do not name), :mod:`.frame_handler`
(the raw frame's path, generated per generation of sets), :mod:`.reloads` (new sets built on a
worker thread), :mod:`.outages` (the interface going and coming back) and :mod:`.status`
(counters, status frame, systemd STATUS). :mod:`.daemon_config` reads its configuration,
:mod:`.active_sets` loads the sets from files or from the sensor, :mod:`.sd_notify` talks to
systemd, :mod:`.service_install` installs the units, and :mod:`.recording` turns bus traffic
into a session (the demo), reading it, as ``canical record`` does, through :mod:`.raw_bus` (on
SocketCAN the daemon's own raw socket behind python-can's public bus class). Imports
:mod:`canical.device` and the rings below it.

The modules are imported where used (``canical.bus.daemon`` and so on): the package itself
imports nothing, so a command that needs one part does not load python-can and cantools for
the others.
"""

# The package's public face: the submodules other rings and the tests import;
# tests/test_rings.py keeps this list equal to those imports.
__all__ = [
    "active_sets",
    "bias_tracking",
    "daemon",
    "daemon_config",
    "link",
    "raw_bus",
    "recording",
    "reloads",
    "sd_notify",
    "service_install",
    "socketcan",
    "socketcan_constants",
    "status",
]

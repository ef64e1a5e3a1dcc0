"""One module per ``canical`` command; each exposes ``register(subparsers)``.

Only the command that runs is imported (see :mod:`canical.commands.cli`): the others'
dependencies (scipy, matplotlib, canopen) would make every start, and every
``canical push`` on a slow vehicle computer, pay for all of them.
"""

# The package's public face: the submodules (and names) other rings and the tests import;
# tests/test_rings.py keeps this list equal to those imports.
__all__ = [
    "COMMANDS",
    "apply",
    "canlog_args",
    "cli",
    "demo_bus",
    "emulate",
    "serve",
    "sign",
    "simulate_fleet",
    "stop_signals",
]

# name -> one-line help, in the order ``canical --help`` lists them
COMMANDS = {
    "calibrate": "fit a turntable session and write a coefficient set",
    "apply": "correct raw samples in a CSV with a coefficient set",
    "demo": "simulate, calibrate and compare the models, no hardware needed",
    "record": "record a calibration session from the bus into a CAN log",
    "serve": "correct raw gyro frames on a CAN bus in real time (daemon)",
    "push": "download coefficient sets to the IMU (CANopen SDO) and activate them",
    "pull": "upload the IMU's active coefficient sets (verified) to YAML",
    "emulate": "run an emulated IMU node (CANopen) on a CAN interface",
    "noise": "Allan deviation of a static record: angle/rate random walk, bias instability",
    "export": "write coefficient sets as a DCF any CANopen tool can download to the IMU",
    "install-service": "install the daemon as a systemd service (/opt/canical, /etc/canical, units)",
    "simulate": "write a simulated session, drive, triad (CSV, or a CAN log in your DBC's layout) or fleet",
    "fleet": "collect vehicles' field logs into a Parquet dataset (ingest) and judge each sensor (analyse)",
    "keygen": "write a key pair to sign coefficient sets with (NAME.key, NAME.pub)",
    "sign": "sign a coefficient set file (Ed25519): content, sensor and version",
    "verify": "say whether a coefficient set file is signed by a trusted key (exit 0 or 2)",
    "provision": "give an IMU the lab's public key it checks signed sets against (once; --close)",
}

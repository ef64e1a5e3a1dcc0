"""The IMU's CAN frames, as the DBC declares them: the single source of their layout.

:mod:`.imu_frames` loads the DBC and names the IMU's frame set; :mod:`.codec` encodes and
decodes them, through codecs :mod:`.compiler` builds from the DBC at start (struct plus
scales and masks, proven equal to cantools). Shared by the daemon, the recorder, the log
reader and the emulated IMU; imports only the ground floor.
"""

# The package's public face: the submodules (and names) other rings and the tests import;
# tests/test_rings.py keeps this list equal to those imports.
__all__ = [
    "codec",
    "compiler",
    "dbc_files",
    "frame_match",
    "imu_dictionary",
    "imu_frames",
]

"""The IMU as a CANopen device: its coefficient banks, the SDO download, and its emulation.

:mod:`.bank_payload` lays a set out in a bank's bytes, :mod:`.bank_signature` its signature
(and the check a device makes before it activates a signed bank), :mod:`.provisioning` gives a
device the key it checks with, :mod:`.coefficient_banks` holds the
device's banks A/B per axis, :mod:`.sdo_download` pushes and pulls sets over SDO,
:mod:`.can_network` opens the CANopen network, :mod:`.emulated_imu` is the emulated node
(streaming simulated frames, evaluating with the C firmware through :mod:`.firmware_eval`),
:mod:`.dcf_export` writes sets as a DCF. The object dictionary itself is the ground floor's
:mod:`canical.frames.imu_dictionary`, because sets and frames need its names too.
"""

# The package's public face: the submodules (and names) other rings and the tests import;
# tests/test_rings.py keeps this list equal to those imports.
__all__ = [
    "bank_payload",
    "bank_signature",
    "can_network",
    "coefficient_banks",
    "dcf_export",
    "emulated_imu",
    "firmware_eval",
    "provisioning",
    "sdo_download",
]

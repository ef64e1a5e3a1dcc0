"""Entries of the shipped IMU object dictionary, read through the typed accessors."""

from __future__ import annotations

import pytest

from canical.errors import CanicalError
from canical.frames.imu_dictionary import AXES, default_value, imu_objects, member, object_dictionary


def test_record_members_and_defaults() -> None:
    od = object_dictionary(5)
    objects = imu_objects()
    # TPDO COB-ID bases (node id 1 resolved): 0x180, 0x280, 0x380 as CANopen assigns them.
    assert objects.tpdo_cob_ids == (0x180, 0x280, 0x380)
    for axis in AXES:
        index, sub = objects.rated_range[axis]
        assert default_value(member(od, index, sub)) > 0


def test_member_of_a_plain_variable_is_an_error_naming_it() -> None:
    od = object_dictionary(1)
    with pytest.raises(CanicalError, match="'Coefficient bank capacity' is a variable"):
        member(od, "Coefficient bank capacity", 1)

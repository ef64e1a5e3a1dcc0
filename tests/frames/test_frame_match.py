"""J1939 messages are recognised by their parameter group, other messages by their exact id."""

from __future__ import annotations

from pathlib import Path

import cantools
import pytest
from hypothesis import given
from hypothesis import strategies as st

from canical.frames.frame_match import ANY_SOURCE, FrameMatcher, frame_match, parse_j1939_source

DATA = Path(__file__).resolve().parents[1] / "data"
J1939 = cantools.database.load_file(str(DATA / "vendor_imu_j1939.dbc"), strict=False)
PLAIN = cantools.database.load_file(str(DATA / "vendor_imu_ext.dbc"), strict=False)


def j1939_id(priority: int, pf: int, ps: int, source: int) -> int:
    return priority << 26 | pf << 16 | ps << 8 | source


@given(priority=st.integers(0, 7))
def test_a_pdu2_group_at_any_priority_from_its_source(priority: int) -> None:
    match = frame_match(J1939.get_message_by_name("ANGRATE"))  # PGN 0xFF2A from 0x10
    assert match.matches(j1939_id(priority, 0xFF, 0x2A, 0x10), True)
    assert not match.matches(j1939_id(priority, 0xFF, 0x2A, 0x11), True)  # another node's
    assert not match.matches(j1939_id(priority, 0xFF, 0x2B, 0x10), True)  # another group
    assert not match.matches(j1939_id(priority, 0xFF, 0x2A, 0x10), False)


@given(source=st.integers(0, 255), priority=st.integers(0, 7))
def test_any_source_or_a_configured_one(source: int, priority: int) -> None:
    message = J1939.get_message_by_name("ANGRATE")
    assert frame_match(message, ANY_SOURCE).matches(j1939_id(priority, 0xFF, 0x2A, source), True)
    configured = frame_match(message, 0x80)
    assert configured.matches(j1939_id(priority, 0xFF, 0x2A, source), True) == (source == 0x80)


@given(destination=st.integers(0, 255))
def test_a_pdu1_group_to_any_destination(destination: int) -> None:
    match = frame_match(J1939.get_message_by_name("TEMP_REQ"))  # PF 0xEF: PDU1, from 0x10
    assert match.matches(j1939_id(3, 0xEF, destination, 0x10), True)
    assert not match.matches(j1939_id(3, 0xEE, destination, 0x10), True)


def test_a_message_not_marked_j1939_is_its_exact_id() -> None:
    message = PLAIN.get_message_by_name("ANGRATE")
    match = frame_match(message, ANY_SOURCE)
    assert match.exact and match.matches(message.frame_id, True)
    assert not match.matches(message.frame_id ^ 0x1C000000, True)  # another priority: another message
    assert match.describe() == "id 0x18ff2a10"
    assert frame_match(J1939.get_message_by_name("ANGRATE"), ANY_SOURCE).describe() == \
        "J1939 PGN 0x0ff2a (65322), any source"


def test_the_matcher_takes_exact_ids_first_then_groups() -> None:
    exact = frame_match(PLAIN.get_message_by_name("IMU_TEMP"))
    group = frame_match(J1939.get_message_by_name("ANGRATE"), ANY_SOURCE)
    matcher = FrameMatcher([(exact, "temp"), (group, "rate")])
    assert matcher.get(0x18FF2B10, True) == "temp"
    assert matcher.get(j1939_id(2, 0xFF, 0x2A, 0x33), True) == "rate"
    assert matcher.get(0x18FF2C10, True) is None and matcher.get(0x123, False) is None


@pytest.mark.parametrize(("value", "expected"), [(None, None), ("any", "any"), (0x80, 0x80), ("0x80", 0x80),
                                                 (0, 0), (253, 253)])
def test_a_source_address_is_any_or_0_to_253(value, expected) -> None:
    assert parse_j1939_source(value, "j1939.source_address") == expected


@pytest.mark.parametrize("value", [254, 255, -1, "all", True, 1.5])
def test_a_bad_source_address_is_one_line_naming_where(value) -> None:
    with pytest.raises(ValueError, match=r"^--j1939-source: must be 'any' or a source address 0\.\.253"):
        parse_j1939_source(value, "--j1939-source")

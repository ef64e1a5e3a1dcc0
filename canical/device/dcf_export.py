"""A DCF (CiA 306 device configuration file) that carries coefficient sets to the IMU.

It is the IMU's EDS, text for text, with ``ParameterValue`` filled for each set's bank
(Content as the hex of the set's canonical JSON, which is how DOMAIN values are
written, its CRC32, and a signed set's Signature, after them in sub-index order: a Content
write clears the bank's Signature) and for the active-bank selector, plus the
``[DeviceComissioning]`` section naming the node. A CANopen configuration tool
downloads writable objects with a ParameterValue in ascending index order, so the
banks (0x2210-0x2215) are written before the selector (0x2220) activates them in one
write, under the device's own checks, exactly as ``canical push`` does. What a DCF
cannot do is choose the inactive bank: ``bank`` fixes it (a device refuses a write to
the bank it runs, and the download stops there), and it cannot store, since 0x1010
comes first in index order: write ``save`` to 0x1010 sub 1 afterwards.

Pure: text in, text out.
"""

from __future__ import annotations

import re
from collections.abc import Mapping

from canical.device.bank_payload import CouplingPayload, encode_set
from canical.frames.imu_dictionary import BANKS, ImuObjects, pack_active
from canical.sets.coefficients import CoefficientSet

_SECTION = re.compile(r"^\[([^\]]+)\]\s*$")


def section_name(index: int, subindex: int | None) -> str:
    """The EDS section of an object (``2210``) or of a sub-entry (``2210sub1``)."""
    return f"{index:04X}" if subindex is None else f"{index:04X}sub{subindex:X}"


def bank_values(objects: ImuObjects, sets: dict[str, CoefficientSet], bank: str,
                coupling: CouplingPayload | None = None,
                signatures: Mapping[str, bytes] | None = None) -> dict[str, str]:
    """ParameterValue per EDS section: each set in ``bank`` of its axis, an IMU set's ``coupling``
    in coupling bank ``bank``, the banks' ``signatures`` (by axis, ``"imu"`` for the coupling
    bank's; a device with a trust key activates nothing without), and the selector."""
    if bank not in BANKS:
        raise ValueError(f"bank {bank!r}: A or B")
    signatures = signatures or {}
    values: dict[str, str] = {}
    for axis, cset in sorted(sets.items()):
        ref = objects.bank(axis, bank)
        content, crc = encode_set(cset)
        values[section_name(ref.index, ref.content)] = content.hex().upper()
        values[section_name(ref.index, ref.crc)] = f"0x{crc:08X}"
        if signatures.get(axis):
            values[section_name(ref.index, ref.signature)] = signatures[axis].hex().upper()
    if coupling is not None:
        cref = objects.coupling_bank(bank)
        values[section_name(cref.index, cref.content)] = coupling.content.hex().upper()
        values[section_name(cref.index, cref.crc)] = f"0x{coupling.crc:08X}"
        values[section_name(cref.index, cref.imu_set_id)] = f"0x{coupling.imu_set_id:08X}"
        if signatures.get("imu"):
            values[section_name(cref.index, cref.signature)] = signatures["imu"].hex().upper()
    index, sub = objects.active_banks
    selector = pack_active({axis: bank for axis in sets}, None if coupling is None else bank)
    values[section_name(index, sub if sub else None)] = f"0x{selector:02X}"
    return values


def dcf_text(eds: str, values: dict[str, str], *, node_id: int, bitrate_kbit: int, name: str) -> str:
    """The EDS text with ParameterValue lines set in the named sections and the commissioning
    section added (CiA 306 spells it ``DeviceComissioning``)."""
    sections = {s.upper(): v for s, v in values.items()}
    out: list[str] = []
    current: str | None = None
    missing = set(sections)

    def close() -> None:
        if current is not None and current in sections:
            while out and not out[-1].strip():
                out.pop()  # the value belongs to its section, before the blank line
            out.append(f"ParameterValue={sections[current]}")
            out.append("")
            missing.discard(current)

    for line in eds.splitlines():
        match = _SECTION.match(line)
        if match:
            close()
            current = match.group(1).upper()
            if current == "DEVICECOMISSIONING":
                raise ValueError("the EDS already has a DeviceComissioning section")
        elif current in sections and line.split("=", 1)[0].strip().lower() == "parametervalue":
            continue  # replaced
        elif current == "FILEINFO" and line.startswith("FileName="):
            line = f"FileName={name}"
        out.append(line)
    close()
    if missing:
        raise ValueError(f"sections not in the EDS: {', '.join(sorted(missing))}")
    out += [
        "",
        "[DeviceComissioning]",
        f"NodeID=0x{node_id:02X}",
        "NodeName=canical IMU",
        f"Baudrate={bitrate_kbit}",
        "NetNumber=1",
        "NetworkName=canical",
        "CANopenManager=0",
        "",
    ]
    return "\n".join(out)

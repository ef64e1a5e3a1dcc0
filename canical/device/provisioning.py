"""Giving an IMU the lab's public key over SDO, once: write it, read it back, close provisioning.

Why apart from push and pull: provisioning is done once per device, at the lab or the end of
line, and closing it cannot be undone (the device then refuses any other key for good), so it
is its own step with its own checks: the key read back before anything is closed, and a device
already closed answered with what it holds rather than a bare refusal.
"""

from __future__ import annotations

from dataclasses import dataclass

from canical.device.sdo_download import ImuClient
from canical.errors import CanicalError
from canical.frames.imu_dictionary import PROVISION_CLOSE_SIGNATURE, PROVISIONING_OPEN, TRUST_KEY_BYTES
from canical.sets.signing import key_id_of


@dataclass(frozen=True)
class DeviceTrust:
    """What a device trusts after provisioning: its key's id, whether provisioning is still open,
    and its anti-rollback counter."""

    key_id: str
    open: bool
    counter: int


def provision(client: ImuClient, key: bytes, *, close: bool) -> DeviceTrust:
    """Write ``key`` as the device's trust key (unless a closed device already holds it), read it
    back, and with ``close`` close provisioning; one CanicalError line when the device holds or
    takes another key."""
    o = client.objects
    where = f"node 0x{client.node_id:02x}"
    if client.read_uint(o.provisioning, "reading the provisioning state") != PROVISIONING_OPEN:
        held = held_key(client)
        if held != key:
            raise CanicalError(f"{where}: provisioning is closed with key {key_id_of(held)}: it takes no "
                               f"other key (not {key_id_of(key)})")
        return state(client)
    client.download(o.trust_key, key, "writing the trust key (0x2232)")
    if held_key(client) != key:
        raise CanicalError(f"{where}: the trust key read back differs from the one written (another writer "
                           "on the bus?); provisioning left open")
    if close:
        client.write_uint(o.provisioning, PROVISION_CLOSE_SIGNATURE, 4, "closing provisioning (0x2233)")
    return state(client)


def held_key(client: ImuClient) -> bytes:
    held = client.upload(client.objects.trust_key, "reading the trust key (0x2232)")
    if len(held) != TRUST_KEY_BYTES:
        raise CanicalError(f"node 0x{client.node_id:02x}: trust key of {len(held)} bytes, "
                           f"not {TRUST_KEY_BYTES}")
    return held


def state(client: ImuClient) -> DeviceTrust:
    o = client.objects
    opened = client.read_uint(o.provisioning, "reading the provisioning state") == PROVISIONING_OPEN
    counter = client.read_uint(o.rollback_counter, "reading the rollback counter (0x2234)")
    return DeviceTrust(key_id_of(held_key(client)), opened, counter)

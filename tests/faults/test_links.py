"""The link rig's pure parts: MAVLink frame splitting (tests/faults/links.py) and the profiles."""

from __future__ import annotations

import struct
from typing import Any

import pytest
from pymavlink.dialects.v10 import ardupilotmega as v1
from pymavlink.dialects.v20 import ardupilotmega as v2

from tests.faults.links import COMMAND_LONG, PROFILES, LinkProfile, message_id, payload, split_mavlink
from tests.faults.proxy import FaultProxy


def frame(msg: Any, mav: Any) -> bytes:
    return bytes(msg.pack(mav))


def test_frames_are_cut_whole_across_chunks_with_junk_and_signatures() -> None:
    plain = v2.MAVLink(None, srcSystem=1, srcComponent=1)
    signed = v2.MAVLink(None, srcSystem=1, srcComponent=191)
    signed.signing.secret_key = bytes(32)
    signed.signing.sign_outgoing = True
    old = v1.MAVLink(None, srcSystem=2, srcComponent=1)
    command = v2.MAVLink_command_long_message(1, 1, 176, 3, 1, 4, 0, 0, 0, 0, 0)
    frames = [
        frame(v2.MAVLink_heartbeat_message(2, 3, 81, 4, 4, 3), plain),
        frame(command, signed),
        frame(v1.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3), old),
    ]
    assert len(frames[1]) == 12 + frames[1][1] + 13  # signed: 13 bytes more
    stream = b"\x00junk" + b"".join(frames)
    buffer, out = bytearray(), []
    for i in range(0, len(stream), 7):  # 7-byte chunks: every frame arrives in pieces
        buffer += stream[i : i + 7]
        out += split_mavlink(buffer)
    assert out == [b"\x00junk", *frames] and not buffer
    assert [message_id(f) for f in out] == [None, 0, COMMAND_LONG, 0]
    # MAVLink 2 trims trailing zeros of the payload; the confirmation still reads back.
    cmd, _ts, _tc, confirmation = struct.unpack_from("<HBBB", payload(frames[1]), 28)
    assert (cmd, confirmation) == (176, 3)
    unconfirmed = frame(v2.MAVLink_command_long_message(1, 1, 176, 0, 1, 4, 0, 0, 0, 0, 0), plain)
    assert struct.unpack_from("<HBBB", payload(unconfirmed), 28)[3] == 0


@pytest.mark.parametrize("profile", list(PROFILES.values()), ids=list(PROFILES))
def test_profiles_set_both_directions_and_scale_outages(profile: LinkProfile) -> None:
    proxy = FaultProxy(1)
    profile.apply(proxy)
    for faults in (proxy.up, proxy.down):
        assert (faults.delay_s, faults.jitter_s, faults.spike_rate) == (
            profile.delay_s,
            profile.jitter_s,
            profile.spike_rate,
        )
    assert profile.outage_wall_s(8.0) == profile.outage_s / 8.0
    assert profile.outage_wall_s(0.5) == profile.outage_s

"""The sans-I/O session layer, strict bodies, must-ignore, replay thinning and the agent's limits."""

from __future__ import annotations

import json
import zlib

import pytest

from agent.link import thin_replay
from protocol.packets import (
    Close,
    CloseReason,
    RequestCid,
    ResponseCid,
    SetParameters,
    StatusReport,
    SyncSignal,
)
from protocol.session import (
    ACTIONS,
    V1_DAEMON,
    ClientHandshake,
    Code,
    Refused,
    ServerHandshake,
    action_for,
    choose_version,
)
from protocol.wire import FRAME_VERSION, HEADER, MAGIC, ProtocolError, decode_body, decode_one, encode

KEY = bytes(range(32))


def _run(client: ClientHandshake, server: ServerHandshake):  # type: ignore[no-untyped-def]
    challenge = server.on_hello(decode_one(encode(client.hello(), 1)).body)
    proof = client.on_challenge(decode_one(encode(challenge, 1, server.version)).body)
    authenticated = server.on_proof(decode_one(encode(proof, 2)).body)
    accepted = server.accept(5, None, 1.0)
    return authenticated, client.on_answer(decode_one(encode(accepted, 2, server.version)).body)


@pytest.mark.parametrize(
    ("client_versions", "server_versions", "expected"),
    [((1, 2), (1, 2), 2), ((1,), (1, 2), 1), ((1, 2), (1,), 1)],
)
def test_versions_are_negotiated_to_the_highest_common_one(
    client_versions: tuple[int, ...], server_versions: tuple[int, ...], expected: int
) -> None:
    client = ClientHandshake("d-1", KEY, versions=client_versions)
    server = ServerHandshake(lambda _: KEY, versions=server_versions)
    authenticated, accepted = _run(client, server)
    assert authenticated.version == accepted.version == expected and accepted.cid == 5


def test_a_v1_peer_gets_v1_shapes_and_a_v1_hello_has_no_v2_field() -> None:
    client = ClientHandshake("d", KEY, versions=[1])
    hello = json.loads(encode(client.hello(), 1)[16:])
    assert "versions" not in hello and hello["protocol_version"] == 1
    server = ServerHandshake(lambda _: KEY)
    challenge = server.on_hello(RequestCid.model_validate(hello))
    assert server.version == 1
    server.on_proof(client.on_challenge(challenge))
    accepted = json.loads(encode(server.accept(1, None, None), 1, server.version)[16:])
    assert not {"protocol_version", "lost", "code"} & set(accepted)
    refusal = [json.loads(encode(b, 1, 1)[16:]) for b in server.refusal(Code.FLEET_FULL, "full")]
    assert all("code" not in r and "retry_after_s" not in r for r in refusal)


@pytest.mark.parametrize(
    ("client_versions", "offer", "server_versions", "grant", "expected"),
    [
        ((1, 2), True, (1, 2), True, True),
        ((1, 2), False, (1, 2), True, False),  # not offered
        ((1, 2), True, (1, 2), False, False),  # not granted
        ((1,), True, (1, 2), True, False),  # a version-1 session has no capabilities
        ((1, 2), True, (1,), True, False),
    ],
)
def test_compact_status_is_a_v2_capability_both_sides_must_want(
    client_versions: tuple[int, ...],
    offer: bool,
    server_versions: tuple[int, ...],
    grant: bool,
    expected: bool,
) -> None:
    client = ClientHandshake("d-1", KEY, versions=client_versions, compact_status=offer)
    server = ServerHandshake(lambda _: KEY, versions=server_versions, compact_status=grant)
    authenticated, accepted = _run(client, server)
    assert accepted.compact_status is expected and server.compact_status is expected
    assert (authenticated.request.compact_status is True) == (offer and accepted.version >= 2)
    # The status encoding follows: 0x82 only on a negotiated v2 session, JSON otherwise.
    status = StatusReport(time=1.0, mode="GUIDED")
    frame = encode(status, 3, accepted.version, compact=accepted.compact_status)
    assert frame[3] == (0x82 if expected else 2)
    decoded = decode_one(frame)
    assert decoded.body == status and decoded.compact is expected
    # Never a v2 field on a v1 session, even if a caller set it.
    v1_accepted = encode(ResponseCid(outcome="accepted", cid=1, compact_status=True), 1, 1)
    assert b"compact_status" not in v1_accepted


def test_a_codeless_refusal_of_a_v2_hello_means_a_v1_daemon() -> None:
    client = ClientHandshake("d", KEY)
    client.hello()
    old = Close(reason=CloseReason.PROTOCOL_ERROR, message="body at versions: Extra inputs are not permitted")
    with pytest.raises(Refused) as caught:
        client.on_challenge(old)
    assert caught.value.code == V1_DAEMON


def test_wrong_keys_are_refused_both_ways() -> None:
    server = ServerHandshake(lambda _: KEY)
    client = ClientHandshake("d", bytes(32))
    server.on_hello(client.hello())
    proof = client.on_challenge(ResponseCid(outcome="challenge", server_nonce=server.server_nonce))
    with pytest.raises(Refused) as caught:
        server.on_proof(proof)
    assert caught.value.code == Code.WRONG_KEY and caught.value.action == "stop"
    # an impostor daemon that cannot prove the key
    honest = ClientHandshake("d", KEY)
    honest.hello()
    honest.on_challenge(ResponseCid(outcome="challenge", server_nonce="ab" * 16))
    with pytest.raises(Refused, match="could not prove"):
        honest.on_answer(ResponseCid(outcome="accepted", cid=1, server_proof="0" * 64))


def test_every_code_has_an_action_and_unknown_codes_retry() -> None:
    assert set(ACTIONS) == {c.value for c in Code}
    assert action_for("something_new") == "retry" and action_for(None) == "retry"
    assert choose_version([3, 4]) is None and choose_version([1, 2, 9]) == 2


def _decode(ptype: int, body: str) -> object:
    return decode_body(ptype, body.encode())


@pytest.mark.parametrize(
    ("ptype", "body", "where"),
    [
        (2, '{"time": 1, "armed": "yes"}', "armed"),
        (2, '{"time": 1, "step": "3"}', "step"),
        (2, '{"time": 1, "step": 2.0}', "step"),
        (2, '{"time": 1, "gps": {"fix": 3.0}}', "gps.fix"),
        (5, '{"mission_id": "m", "step": 1, "kind": "finished", "kind": "release"}', "duplicate key"),
        (2, '{"time": Infinity}', "not JSON"),
        (
            4,
            '{"mission_id": "m", "actions": [{"kind": "hold", "step": 0, "seconds": 1, "at": 2}]}',
            "actions",
        ),
        (3, '{"geofence": {"exclusion": []}}', "geofence"),
    ],
)
def test_strict_bodies(ptype: int, body: str, where: str) -> None:
    with pytest.raises(ProtocolError, match=where):
        _decode(ptype, body)


def test_unknown_fields_outside_commands_are_ignored() -> None:
    status = _decode(2, '{"time": 1, "new_field": {"x": 1}, "battery": {"pct": 50, "temperature": 30}}')
    assert isinstance(status, StatusReport) and status.battery.pct == 50
    sync = _decode(5, '{"mission_id": "m", "step": 1, "kind": "release", "priority": 3}')
    assert sync == SyncSignal(mission_id="m", step=1, kind="release")
    assert isinstance(_decode(2, '{"time": 1, "heading_deg": 90}'), StatusReport)  # an int for a float


def test_keepalive_body_is_the_empty_object_of_the_spec() -> None:
    frame = encode(SetParameters(), 1)
    assert frame[16:] == b"{}" and frame[:16] == HEADER.pack(MAGIC, FRAME_VERSION, 3, 1, 2, zlib.crc32(b"{}"))


def test_replay_is_thinned_keeping_every_state_change_in_order() -> None:
    reports = [StatusReport(time=i, completed_step=i // 100) for i in range(600)]
    kept = thin_replay(reports, 300)
    assert len(kept) == 300 and [r.time for r in kept] == sorted(r.time for r in kept)
    assert {r.completed_step for r in kept} == set(range(6)) and kept[-1] is reports[-1]
    assert thin_replay(reports[:10], 300) == reports[:10]

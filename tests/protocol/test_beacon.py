"""The release beacon's codec and hash chain (protocol/beacon.py): what an agent accepts, and why."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol.beacon import (
    MAX_CHAIN_STEPS,
    VALUE_BYTES,
    Beacon,
    BeaconError,
    ReleaseChain,
    ReleaseVerifier,
    chain_hash,
    decode_beacon,
    encode_beacon,
    parse_beacon_address,
)
from protocol.packets import PerformActions, RequestCid
from protocol.session import ClientHandshake, ServerHandshake

MISSION_IDS = st.text(st.characters(codec="utf-8", exclude_categories=("Cs",)), min_size=1, max_size=16)


def test_each_step_reveals_a_value_that_hashes_back_to_the_anchor() -> None:
    chain = ReleaseChain(5, seed=b"s" * 16)
    for step in range(5):
        value = chain.value(step)
        assert value is not None
        link = value
        for _ in range(step + 1):
            link = chain_hash(link)
        assert link == chain.anchor
    assert chain.value(5) is None and chain.value(-1) is None


def test_the_verifier_takes_releases_in_order_with_gaps_and_never_twice() -> None:
    chain = ReleaseChain(10)
    verifier = ReleaseVerifier(chain.anchor)
    assert verifier.accept(2, chain.value(2) or b"")  # steps 0 and 1 had no beacon (lost): fine
    assert not verifier.accept(2, chain.value(2) or b"")  # a replay of an accepted release
    assert not verifier.accept(1, chain.value(1) or b"")  # an older release after a newer one
    assert verifier.accept(3, chain.value(3) or b"")
    assert verifier.accept(9, chain.value(9) or b"")


def test_nothing_but_the_daemons_chain_passes() -> None:
    chain, other = ReleaseChain(4), ReleaseChain(4)
    verifier = ReleaseVerifier(chain.anchor)
    assert not verifier.accept(0, other.value(0) or b"")  # another mission's (or daemon's) chain
    assert not verifier.accept(1, chain.value(0) or b"")  # a released value for the next step
    assert not verifier.accept(0, chain.anchor)  # the anchor every drone knows proves nothing
    assert not verifier.accept(0, b"\0" * VALUE_BYTES)
    assert not verifier.accept(0, (chain.value(0) or b"")[:8])
    assert not verifier.accept(MAX_CHAIN_STEPS + 5, b"\0" * VALUE_BYTES)  # bounded work
    assert verifier.accept(0, chain.value(0) or b"")


def test_a_chain_is_bounded() -> None:
    with pytest.raises(ValueError, match=r"1\.\.4096"):
        ReleaseChain(MAX_CHAIN_STEPS + 1)
    with pytest.raises(ValueError, match="16 bytes"):
        ReleaseVerifier(b"short")


@given(MISSION_IDS, st.integers(0, 2**32 - 1), st.binary(min_size=VALUE_BYTES, max_size=VALUE_BYTES))
def test_a_beacon_decodes_to_what_was_encoded(mission_id: str, step: int, value: bytes) -> None:
    if len(mission_id.encode()) > 64:
        return
    assert decode_beacon(encode_beacon(mission_id, step, value)) == Beacon(mission_id, step, value)


@given(st.binary(max_size=120))
def test_any_datagram_decodes_or_says_why_not(data: bytes) -> None:
    try:
        beacon = decode_beacon(data)
    except BeaconError as exc:
        assert str(exc)
    else:
        assert encode_beacon(beacon.mission_id, beacon.step, beacon.value) == data


def test_malformed_beacons_are_named() -> None:
    good = encode_beacon("m-1", 3, b"v" * VALUE_BYTES)
    with pytest.raises(BeaconError, match="magic"):
        decode_beacon(b"XXXX" + good[4:])
    with pytest.raises(BeaconError, match="layout 9"):
        decode_beacon(good[:4] + b"\x09" + good[5:])
    with pytest.raises(BeaconError, match="expected"):
        decode_beacon(good + b"x")
    with pytest.raises(ValueError, match="u32"):
        encode_beacon("m-1", 2**32, b"v" * VALUE_BYTES)


def test_the_offer_and_the_anchor_are_v2_fields() -> None:
    """A v2 agent offers beacons with its proof; a v1 session never sees either field."""
    client = ClientHandshake("a1", b"k" * 32, release_beacon=True)
    server = ServerHandshake(lambda _identity: b"k" * 32)
    challenge = server.on_hello(client.hello())
    proof = client.on_challenge(challenge)
    assert isinstance(proof, RequestCid) and proof.release_beacon is True
    assert server.on_proof(proof).request.release_beacon is True
    v1 = ClientHandshake("a1", b"k" * 32, versions=(1,), release_beacon=True)
    v1_server = ServerHandshake(lambda _identity: b"k" * 32)
    assert v1.on_challenge(v1_server.on_hello(v1.hello())).release_beacon is None

    from protocol.wire import encode

    body = PerformActions(mission_id="m", release_anchor="ab" * 16)
    assert b"release_anchor" in encode(body, 1, 2)
    assert b"release_anchor" not in encode(body, 1, 1)


def test_beacon_addresses_are_ipv4_and_port() -> None:
    assert parse_beacon_address("127.255.255.255:14650") == ("127.255.255.255", 14650)
    for bad, why in (
        ("localhost:1", "not an IPv4"),
        ("1.2.3.4", "expected IPv4:PORT"),
        ("1.2.3.4:0", "1..65535"),
    ):
        with pytest.raises(ValueError, match=why):
            parse_beacon_address(bad)

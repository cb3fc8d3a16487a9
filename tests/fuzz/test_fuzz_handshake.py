"""Bounded CI run of the handshake fuzz target (fuzz/fuzz_handshake.py): seeds + 3000 mutations."""

from __future__ import annotations

import pytest

from fuzz.fuzz_handshake import _client, _server, mutation_loop, seed_cases
from fuzz.fuzz_handshake import test_one_input as run_case  # aliased: pytest must not collect it
from protocol.session import Refused
from protocol.wire import FrameDecoder


def test_seeds_complete_or_are_refused_as_intended() -> None:
    """Valid transcripts authenticate in both roles (so mutations start deep); bad ones are refused."""
    outcomes = []
    for case in seed_cases():
        run_case(case)
        bodies = [f.body for f in FrameDecoder().feed(case[1:])]
        try:
            (_client if case[0] & 1 else _server)(bodies)
            outcomes.append("ok")
        except Refused as exc:
            outcomes.append(exc.code or "codeless")
    assert outcomes == ["ok", "ok", "unknown_identity", "wrong_key", "ok", "ok", "fleet_full", "v1_daemon"]


def test_a_forged_proof_never_authenticates() -> None:
    hello, proof = FrameDecoder().feed(seed_cases()[0][1:])
    forged = proof.body.model_copy(update={"proof": "f" * 64})
    with pytest.raises(Refused, match="wrong key"):
        _server([hello.body, forged])


def test_handshake_over_3000_mutations() -> None:
    ran = mutation_loop(seconds=10.0, seed=20_261_130, max_cases=3000)
    assert ran >= 500  # normally all 3000 in a few seconds; the time cap guards slow CI

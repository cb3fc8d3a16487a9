"""Fuzz target for the handshake state machines (protocol/session.py), both roles.

Contract under test: whatever frames a peer sends before ``accepted``, the server and client
handshakes end in a valid outcome or raise :class:`~protocol.session.Refused` /
:class:`~protocol.wire.ProtocolError`, nothing else; and neither side ever authenticates a peer
that did not prove the key (the server's ``Authenticated`` and the client's ``Accepted`` are
checked against independently computed proofs).

A case is a control byte and the frames the peer sends: bit 0 picks the role under test
(0: the daemon's side gets hello + proof; 1: the agent's side gets challenge + answer), bit 7
recomputes every CRC so mutated bodies reach the models. Nonces are fixed so the seeds hold valid
proofs. Mutations are those of fuzz/fuzz_decoder.py.

    python fuzz/fuzz_handshake.py -max_total_time=60      # atheris when installed, else mutations
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make the repository importable
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

try:
    import atheris
except ImportError:
    atheris = None

if atheris is not None:
    with atheris.instrument_imports(include=["protocol"]):
        from protocol import auth
        from protocol.packets import Body, Close, CloseReason, RequestCid, ResponseCid
        from protocol.session import ClientHandshake, Refused, ServerHandshake
        from protocol.wire import PRE_AUTH_MAX_BODY, FrameDecoder, ProtocolError, encode
else:
    from protocol import auth
    from protocol.packets import Body, Close, CloseReason, RequestCid, ResponseCid
    from protocol.session import ClientHandshake, Refused, ServerHandshake
    from protocol.wire import PRE_AUTH_MAX_BODY, FrameDecoder, ProtocolError, encode

from fuzz.fuzz_decoder import mutation_loop as decoder_mutation_loop
from fuzz.fuzz_decoder import split_case

KEY = bytes(range(32))
CLIENT_NONCE = "c1" * 16
SERVER_NONCE = "5e" * 16
IDENTITY = "drone-1"


def _key_for(identity: str) -> bytes | None:
    return None if identity == "unknown" else KEY


def _frames(*bodies: Body) -> bytes:
    return b"".join(encode(body, seq) for seq, body in enumerate(bodies, 1))


def seed_cases() -> list[bytes]:
    """Valid and refused transcripts for both roles."""
    proof = auth.agent_proof(KEY, IDENTITY, SERVER_NONCE, CLIENT_NONCE)
    server_proof = auth.daemon_proof(KEY, IDENTITY, CLIENT_NONCE, SERVER_NONCE)
    hello = RequestCid(identity=IDENTITY, protocol_version=2, versions=[1, 2], client_nonce=CLIENT_NONCE)
    v1_hello = RequestCid(identity=IDENTITY, protocol_version=1, client_nonce=CLIENT_NONCE)
    cases = [
        b"\x80" + _frames(hello, hello.model_copy(update={"proof": proof})),
        b"\x80" + _frames(v1_hello, v1_hello.model_copy(update={"proof": proof, "probe": True})),
        b"\x80" + _frames(hello.model_copy(update={"identity": "unknown"})),
        b"\x80" + _frames(hello, hello.model_copy(update={"proof": "0" * 64})),
        b"\x81"
        + _frames(
            ResponseCid(outcome="challenge", server_nonce=SERVER_NONCE, protocol_version=2),
            ResponseCid(
                outcome="accepted",
                cid=3,
                server_nonce=SERVER_NONCE,
                server_proof=server_proof,
                protocol_version=2,
            ),
        ),
        b"\x81"
        + _frames(
            ResponseCid(outcome="challenge", server_nonce=SERVER_NONCE),
            ResponseCid(outcome="accepted", cid=3, server_proof=server_proof, lost=True),
        ),
        b"\x81" + _frames(ResponseCid(outcome="refused", reason="full", code="fleet_full", retry_after_s=5)),
        b"\x81" + _frames(Close(reason=CloseReason.PROTOCOL_ERROR, message="body at versions: extra")),
    ]
    return cases


def test_one_input(data: bytes) -> None:
    """One case; raises AssertionError (or whatever escaped) on a contract breach."""
    if not data:
        return
    control, payload = split_case(data)
    try:
        bodies = [f.body for f in FrameDecoder(PRE_AUTH_MAX_BODY).feed(payload)][:2]
    except ProtocolError:
        return
    try:
        if control & 1:
            _client(bodies)
        else:
            _server(bodies)
    except (Refused, ProtocolError):
        return


def _server(bodies: list[Body]) -> None:
    server = ServerHandshake(_key_for, nonce=SERVER_NONCE)
    if not bodies:
        return
    server.on_hello(bodies[0])
    if len(bodies) < 2:
        return
    authenticated = server.on_proof(bodies[1])
    request = authenticated.request
    assert request.proof == auth.agent_proof(KEY, request.identity, SERVER_NONCE, request.client_nonce)
    assert server.hello is not None and request.client_nonce == server.hello.client_nonce
    accepted = server.accept(1, None, None)
    assert accepted.outcome == "accepted" and accepted.server_proof is not None


def _client(bodies: list[Body]) -> None:
    client = ClientHandshake(IDENTITY, KEY, nonce=CLIENT_NONCE)
    client.hello()
    if not bodies:
        return
    proof = client.on_challenge(bodies[0])
    assert proof.proof is not None and client.server_nonce is not None
    if len(bodies) < 2:
        return
    accepted = client.on_answer(bodies[1])
    answer = bodies[1]
    assert isinstance(answer, ResponseCid)
    assert answer.server_proof == auth.daemon_proof(KEY, IDENTITY, CLIENT_NONCE, client.server_nonce)
    assert accepted.version in (1, 2) and accepted.cid is not None


def mutation_loop(seconds: float, seed: int = 0, max_cases: int = 10**9) -> int:
    """Mutated seed cases (the decoder target's mutations) until ``seconds`` or ``max_cases``."""
    return decoder_mutation_loop(seed_cases(), seconds, seed, max_cases, target=test_one_input)


def main(argv: list[str]) -> int:
    if atheris is not None:
        if not [a for a in argv[1:] if not a.startswith("-")]:  # no corpus given: start from the seeds
            corpus = Path(tempfile.mkdtemp(prefix="fuzz-handshake-"))
            for number, case in enumerate(seed_cases()):
                (corpus / f"seed-{number}").write_bytes(case)
            argv = [*argv, str(corpus)]
        atheris.Setup(argv, test_one_input)
        atheris.Fuzz()
        return 0
    seconds = next((float(a.split("=", 1)[1]) for a in argv if a.startswith("-max_total_time=")), 60.0)
    print(f"atheris not installed: ran {mutation_loop(seconds)} mutated cases, no failure")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))

"""Coverage-guided fuzz target for the sans-I/O frame decoder (atheris, i.e. libFuzzer for Python).

Contract under test (docs/protocol.md section 1): whatever bytes arrive, split into reads however
the network likes, :class:`protocol.wire.FrameDecoder` yields valid frames or raises
:class:`protocol.wire.ProtocolError`, nothing else; once failed it stays failed; and every frame
it accepts survives an encode/decode round trip unchanged.

The first input byte steers the harness so the fuzzer can reach deep code: its low 5 bits pick
the read size, bit 5 a small body limit (4 KiB) to exercise the size check, bit 7 recomputes the
CRC of every frame in the input, so mutated bodies get past the CRC check into JSON parsing and
the pydantic models instead of dying at the CRC.

Run (coverage-guided; grows the corpus directory given first, writes crashes as crash-*):

    python fuzz/fuzz_decoder.py fuzz/corpus/decoder -max_total_time=300

Without atheris, the same command runs a seeded mutation loop over the corpus for
``-max_total_time`` seconds (no coverage feedback). tests/fuzz/test_fuzz_decoder.py runs the target
over the corpus plus 2000 mutated inputs in CI.
"""

from __future__ import annotations

import json
import random
import sys
import time
import zlib
from collections.abc import Callable
from pathlib import Path

try:
    import atheris
except ImportError:  # the mutation loop below still works
    atheris = None

if atheris is not None:
    with atheris.instrument_imports(include=["protocol"]):
        from protocol.wire import (
            HEADER,
            HEADER_SIZE,
            MAGIC,
            Frame,
            FrameDecoder,
            ProtocolError,
            decode_one,
            encode,
        )
else:
    from protocol.wire import (
        HEADER,
        HEADER_SIZE,
        MAGIC,
        Frame,
        FrameDecoder,
        ProtocolError,
        decode_one,
        encode,
    )

CORPUS = Path(__file__).resolve().parent / "corpus" / "decoder"
SMALL_LIMIT = 4096
READ_SIZES = (1, 2, 3, 5, 7, 13, 16, 17, 31, 64, 100, 257, 1024, 4096, 65_536, 1 << 30)


def fix_crcs(data: bytes) -> bytes:
    """Walk the frames in ``data`` by their headers and rewrite each body CRC to match (bounded)."""
    out = bytearray(data)
    offset = 0
    for _ in range(len(out) // HEADER_SIZE + 1):
        if offset + HEADER_SIZE > len(out) or out[offset : offset + 2] != MAGIC:
            break
        length = int.from_bytes(out[offset + 8 : offset + 12], "big")
        end = offset + HEADER_SIZE + length
        if end > len(out):
            break
        out[offset + 12 : offset + 16] = zlib.crc32(out[offset + HEADER_SIZE : end]).to_bytes(4, "big")
        offset = end
    return bytes(out)


def split_case(data: bytes) -> tuple[int, bytes]:
    """A case's control byte and its payload, CRCs recomputed when bit 7 asks for it."""
    control, payload = data[0], data[1:]
    return control, fix_crcs(payload) if control & 0x80 else payload


def test_one_input(data: bytes) -> None:
    """One fuzz case. Raises AssertionError (or whatever escaped the decoder) on a contract breach."""
    if not data:
        return
    control, payload = split_case(data)
    read_size = READ_SIZES[control & 0x0F]
    decoder = FrameDecoder(SMALL_LIMIT) if control & 0x20 else FrameDecoder()
    frames: list[Frame] = []
    try:
        for start in range(0, len(payload), read_size):
            frames.extend(decoder.feed(payload[start : start + read_size]))
    except ProtocolError:
        try:
            list(decoder.feed(b"FG"))
        except ProtocolError:
            return  # stays failed: correct
        raise AssertionError("decoder accepted bytes after a protocol error") from None
    assert decoder.pending_bytes <= len(payload)
    for frame in frames:
        again = decode_one(encode(frame.body, frame.seq))
        assert again.body == frame.body and again.packet_type == frame.packet_type, frame


# --- mutation (used without atheris, and by the CI test) -------------------------------------------

_JSON_VALUES: tuple[object, ...] = (
    None,
    True,
    0,
    -1,
    2**31,
    2**64,
    1e308,
    -0.0,
    "",
    "x" * 300,
    "\u00e9\u4e2d",
    [],
    {},
    [1, [2, [3]]],
    {"a": {"b": {}}},
)


def _mutate_json(body: bytes, rng: random.Random) -> bytes:
    """Replace, drop or add one field of a JSON object body (keeps it JSON, breaks the schema)."""
    try:
        document = json.loads(body)
    except (ValueError, RecursionError):
        return body
    if not isinstance(document, dict) or not document:
        return json.dumps(rng.choice(_JSON_VALUES)).encode()
    key = rng.choice(sorted(document))
    op = rng.randrange(4)
    if op == 0:
        document[key] = rng.choice(_JSON_VALUES)
    elif op == 1:
        del document[key]
    elif op == 2:
        document[rng.choice(["extra", key + "_", "kind", "step"])] = rng.choice(_JSON_VALUES)
    else:
        inner = document[key]
        if isinstance(inner, dict) and inner:
            inner[rng.choice(sorted(inner))] = rng.choice(_JSON_VALUES)
        elif isinstance(inner, list) and inner:
            inner[rng.randrange(len(inner))] = rng.choice(_JSON_VALUES)
        else:
            document[key] = rng.choice(_JSON_VALUES)
    try:
        return json.dumps(document).encode()
    except (ValueError, RecursionError):
        return body


def _reframe(data: bytes, body: bytes, ptype: int | None = None) -> bytes:
    _, version, old_type, seq, _, _ = HEADER.unpack_from(data)
    return (
        HEADER.pack(MAGIC, version, old_type if ptype is None else ptype, seq, len(body), zlib.crc32(body))
        + body
    )


def mutate(data: bytes, rng: random.Random, others: list[bytes]) -> bytes:
    """One structure-aware or byte-level mutation of a case (control byte included)."""
    control, payload = (data[0], data[1:]) if data else (0, b"")
    op = rng.randrange(10)
    framed = len(payload) >= HEADER_SIZE and payload[:2] == MAGIC
    if op == 0 and framed:  # schema-level: mutate the JSON body, keep the frame valid
        length = int.from_bytes(payload[8:12], "big")
        body = _mutate_json(payload[HEADER_SIZE : HEADER_SIZE + length], rng)
        payload = _reframe(payload, body) + payload[HEADER_SIZE + length :]
    elif op == 1 and framed:  # move a body to another packet type
        length = int.from_bytes(payload[8:12], "big")
        body = payload[HEADER_SIZE : HEADER_SIZE + length]
        payload = _reframe(payload, body, rng.randrange(8))
    elif op == 2 and payload:  # flip bits
        buf = bytearray(payload)
        for _ in range(rng.randint(1, 4)):
            buf[rng.randrange(len(buf))] ^= 1 << rng.randrange(8)
        payload = bytes(buf)
    elif op == 3 and payload:  # truncate
        payload = payload[: rng.randrange(len(payload))]
    elif op == 4:  # insert random bytes
        at = rng.randrange(len(payload) + 1)
        payload = payload[:at] + rng.randbytes(rng.randint(1, 32)) + payload[at:]
    elif op == 5 and len(payload) >= HEADER_SIZE:  # header field: version, type or length
        buf = bytearray(payload)
        field = rng.choice([2, 3, 8])
        if field == 8:
            buf[8:12] = rng.choice([0, 1, SMALL_LIMIT + 1, (1 << 20) + 1, 0xFFFFFFFF]).to_bytes(4, "big")
        else:
            buf[field] = rng.randrange(256)
        payload = bytes(buf)
    elif op == 6 and others:  # splice: this case followed by another one
        payload = payload + rng.choice(others)[1:]
    elif op == 7 and payload:  # duplicate a slice
        a = rng.randrange(len(payload))
        b = min(len(payload), a + rng.randint(1, 64))
        payload = payload[:b] + payload[a:b] + payload[b:]
    else:  # new control byte: other read sizes, limits, CRC fixing
        control = rng.randrange(256)
    return bytes([control]) + payload


def load_corpus(directory: Path = CORPUS) -> list[bytes]:
    return [p.read_bytes() for p in sorted(directory.iterdir()) if p.is_file()]


def mutation_loop(
    corpus: list[bytes],
    seconds: float,
    seed: int = 0,
    max_cases: int = 10**9,
    target: Callable[[bytes], None] | None = None,
) -> int:
    """Run mutated cases through ``target`` (this decoder target by default) until ``seconds`` or
    ``max_cases``; returns the number run."""
    rng = random.Random(seed)
    deadline = time.monotonic() + seconds
    cases = 0
    while cases < max_cases and time.monotonic() < deadline:
        case = rng.choice(corpus)
        for _ in range(rng.randint(1, 3)):
            case = mutate(case, rng, corpus)
        (target or test_one_input)(case)
        cases += 1
    return cases


def main(argv: list[str]) -> int:
    if atheris is not None:
        atheris.Setup(argv, test_one_input)
        atheris.Fuzz()
        return 0
    seconds = next((float(a.split("=", 1)[1]) for a in argv if a.startswith("-max_total_time=")), 60.0)
    dirs = [Path(a) for a in argv[1:] if not a.startswith("-")] or [CORPUS]
    corpus = [case for d in dirs for case in load_corpus(d)]
    cases = mutation_loop(corpus, seconds)
    print(f"atheris not installed: ran {cases} mutated cases without coverage feedback, no failure")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))

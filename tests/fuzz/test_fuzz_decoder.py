"""Bounded CI run of the decoder fuzz target (fuzz/fuzz_decoder.py): corpus + seeded mutations + atheris.

The long, open-ended run is ``python fuzz/fuzz_decoder.py fuzz/corpus/decoder -max_total_time=N``;
here each part is capped (2000 mutated cases, at most ~10 s) so it can run on every commit.
"""

from __future__ import annotations

import importlib.util
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from fuzz.fuzz_decoder import CORPUS, load_corpus, mutation_loop
from fuzz.fuzz_decoder import test_one_input as run_case  # aliased: pytest must not collect it
from protocol.wire import FrameDecoder, ProtocolError

TARGET = CORPUS.parent.parent / "fuzz_decoder.py"


def test_seed_corpus_holds_a_valid_frame_of_every_packet_type() -> None:
    types = set()
    for case in load_corpus():
        try:
            types |= {f.packet_type.value for f in FrameDecoder().feed(case[1:])}
        except ProtocolError:
            continue
    assert types == set(range(7))
    assert len(load_corpus()) >= 30


def test_target_over_the_corpus_and_2000_mutations() -> None:
    """Only ProtocolError may escape the decoder (run_case asserts the rest)."""
    corpus = load_corpus()
    for case in corpus:
        run_case(case)
    ran = mutation_loop(corpus, seconds=10.0, seed=20_240_601, max_cases=2000)
    assert ran >= 500  # normally all 2000 in about a second; the time cap is a guard for slow CI


@pytest.mark.skipif(importlib.util.find_spec("atheris") is None, reason="atheris not installed")
def test_coverage_guided_run_is_clean(tmp_path: Path) -> None:
    """2000 atheris (libFuzzer) executions starting from a copy of the corpus (the copy may grow)."""
    corpus = tmp_path / "corpus"
    shutil.copytree(CORPUS, corpus)
    result = subprocess.run(
        [
            sys.executable,
            str(TARGET),
            str(corpus),
            "-runs=2000",
            "-max_total_time=10",
            f"-artifact_prefix={tmp_path}/",
            "-print_final_stats=1",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    # libFuzzer counts the corpus replay too, so the total can pass -runs by a few.
    assert re.search(r"Done \d+ runs", result.stderr) or "max_total_time" in result.stderr, result.stderr[
        -1000:
    ]
    assert not list(tmp_path.glob("crash-*"))

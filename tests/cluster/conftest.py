"""NATS servers for the cluster tests: ``nats-server -js`` on free loopback ports, always stopped."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from gcs.cluster.natsrun import NatsCluster, NatsServer, missing_reason


@pytest.fixture
def nats_server(tmp_path: Path) -> Iterator[NatsServer]:
    reason = missing_reason()
    if reason is not None:
        pytest.skip(reason)
    server = NatsServer(tmp_path / "nats")
    server.start()
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture
def nats_cluster(tmp_path: Path) -> Iterator[NatsCluster]:
    reason = missing_reason()
    if reason is not None:
        pytest.skip(reason)
    cluster = NatsCluster(tmp_path / "nats")
    cluster.start()
    try:
        yield cluster
    finally:
        cluster.stop()

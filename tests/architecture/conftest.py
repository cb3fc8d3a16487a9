"""The cluster tests' NATS fixture, shared (not copied): the command-port test crosses two daemons."""

from tests.cluster.conftest import nats_server

__all__ = ["nats_server"]

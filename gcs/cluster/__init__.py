"""Several daemons sharing one fleet through NATS JetStream (``gcs serve --cluster``; docs/cluster.md).

Imported only in cluster mode: the embedded default (one daemon, its SQLite file) needs no NATS.
"""

"""Spreading sessions over N ``esa-server`` processes (``--shard i/N``) by a stable hash.

Routing rule (the same in every client, see ``deploy/README.md``)::

    shard_of(id, N) = int.from_bytes(sha256(id.encode("utf-8")).digest()[:8], "big") % N

i.e. the first 8 bytes of the SHA-256 of the UTF-8 session id, read as a big-endian
unsigned 64-bit integer, modulo N. Shard ``i`` serves the keys ``<prefix>/shard/<i>/...``.

The transport that routes over the shards is
:class:`~esa_client.transports.zenoh.ZenohTransport`.
"""

from __future__ import annotations

import hashlib


def shard_of(session_id: str, shards: int) -> int:
    """The shard (0 <= shard < ``shards``) that owns ``session_id``; see the module docstring."""
    if shards < 1:
        raise ValueError(f"expected shards >= 1, got {shards}")
    digest = hashlib.sha256(session_id.encode("utf-8")).digest()
    return int.from_bytes(digest[:8], "big") % shards


def shard_prefix(prefix: str, shard: int) -> str:
    """The key prefix shard ``shard`` serves under ``prefix`` (``esa/v1/shard/1``)."""
    return f"{prefix}/shard/{shard}"

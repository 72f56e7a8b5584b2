"""The ways of reaching the update law, one :class:`~esa_client.transports.base.Transport` each.

- :mod:`~esa_client.transports.base`: the interface sessions and batches are written against;
- :mod:`~esa_client.transports.in_process`: esa-core in this process, no wire;
- :mod:`~esa_client.transports.grpc`: gRPC through the Rust client of ``esa_client._native``
  (TLS and mutual TLS, token, health, one ``StepStream`` per batch);
- :mod:`~esa_client.transports.zenoh`: Zenoh queries to one server or N shards (extra
  ``esa-client[zenoh]``).

Build clients with :class:`esa_client.EsaClient` (``connect``, ``spawn``, ``in_process``),
which picks and owns the transport.
"""

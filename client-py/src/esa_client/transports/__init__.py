"""The ways of reaching the update law, one :class:`~esa_client.transports.base.Transport` each.

- :mod:`~esa_client.transports.base`: the protocol sessions and batches are written against;
- :mod:`~esa_client.transports.stub`: the protocol over protobuf messages, for any stub;
- :mod:`~esa_client.transports.grpcio`: gRPC through grpcio (TLS, one ``StepStream`` per batch);
- :mod:`~esa_client.transports.native`: gRPC through the Rust client of ``esa_client._native``;
- :mod:`~esa_client.transports.in_process`: esa-core in this process, no wire;
- :mod:`~esa_client.transports.zenoh_query`: Zenoh queries (extra ``esa-client[zenoh]``);
- :mod:`~esa_client.transports.sharded`: N shards, one transport each.

Build clients with :class:`esa_client.EsaClient` (``connect``, ``spawn``, ``in_process``),
which picks and owns the transport.
"""

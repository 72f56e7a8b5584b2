"""The ways of reaching the update law, one :class:`~esa_client.transports.base.Transport` each.

:mod:`~esa_client.transports.base` lists them. Build clients with
:class:`esa_client.EsaClient` (``connect``, ``spawn``, ``in_process``), which picks and owns
the transport.
"""

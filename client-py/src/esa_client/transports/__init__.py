"""The transports, one :class:`~esa_client.transports.base.Transport` each; EsaClient picks one."""

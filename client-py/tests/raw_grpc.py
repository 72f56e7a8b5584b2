"""A gRPC peer of the tests' own (grpcio, a dev dependency): the raw and malformed requests the
client never sends, answered by a real server that ``EsaClient.spawn`` started."""

import functools
from typing import Any

import grpc

from esa_client import EsaClient
from esa_client._proto.esa.v1 import esa_pb2_grpc
from esa_client.errors import error_for


@functools.cache
def channel(address: str) -> grpc.Channel:
    """A plaintext channel to ``address``, kept for the test session."""
    # gRPC core would send a Unix socket's path as :authority, which tonic rejects.
    options = [("grpc.default_authority", "localhost")] if address.startswith("unix:") else []
    return grpc.insecure_channel(address, options=options)


def stub(client: EsaClient) -> esa_pb2_grpc.EsaServiceStub:
    """The generated stub on a channel to the server ``client`` spawned."""
    assert client.server is not None
    return esa_pb2_grpc.EsaServiceStub(channel(client.server.address))


def call(rpc: Any, request: Any, timeout: float) -> Any:
    """One raw call; its failure raised as the client's typed error (without the item)."""
    try:
        return rpc(request, timeout=timeout)
    except grpc.RpcError as err:
        raise error_for(err.code().value[0], err.details() or "") from None

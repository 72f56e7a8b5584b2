"""A gRPC peer of the tests' own (grpcio, a dev dependency): the raw and malformed requests the
client never sends, answered by a real server that ``EsaClient.spawn`` started."""

import functools
from typing import Any

import grpc

from esa_client import EsaClient
from esa_client._proto.esa.v1 import esa_pb2
from esa_client.errors import error_for

SERVICE = esa_pb2.DESCRIPTOR.services_by_name["EsaService"]


@functools.cache
def channel(address: str) -> grpc.Channel:
    """A plaintext channel to ``address``, kept for the test session."""
    # gRPC core would send a Unix socket's path as :authority, which tonic rejects.
    options = [("grpc.default_authority", "localhost")] if address.startswith("unix:") else []
    return grpc.insecure_channel(address, options=options)


class Stub:
    """EsaService's unary methods as grpcio callables, named as in the proto.

    Built from the descriptor: the client package ships no grpcio service module.
    """

    def __init__(self, grpc_channel: grpc.Channel) -> None:
        for method in SERVICE.methods:
            if method.client_streaming or method.server_streaming:
                continue
            response = getattr(esa_pb2, method.output_type.name)
            rpc = grpc_channel.unary_unary(
                f"/{SERVICE.full_name}/{method.name}",
                request_serializer=lambda request: request.SerializeToString(),
                response_deserializer=response.FromString,
            )
            setattr(self, method.name, rpc)


def stub(client: EsaClient) -> Any:
    """A :class:`Stub` on a channel to the server ``client`` spawned."""
    assert client.server is not None
    return Stub(channel(client.server.address))


def call(rpc: Any, request: Any, timeout: float) -> Any:
    """One raw call; its failure raised as the client's typed error (without the item)."""
    try:
        return rpc(request, timeout=timeout)
    except grpc.RpcError as err:
        raise error_for(err.code().value[0], err.details() or "") from None

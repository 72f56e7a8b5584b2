"""The Rust gRPC client (``EsaClient.connect(..., transport="native")``) and grpcio answer alike.

The parity tests of the in-process engine (``test_inprocess.py``) run again with the native
client of a second real server in place of the engine: the same random scripts through both
clients give identical answers and states, and every bad input raises the same exception type,
status code, failing item and message. Then what only a remote transport has: TCP, the auth
token, a dead server, a deadline, a closed client.
"""

import importlib.util
import os
import signal
import time
import uuid
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from esa_client import (
    DeadlineExceeded,
    EsaClient,
    ServerUnavailable,
    SessionNotFound,
    StatusCode,
    Unauthenticated,
)
from esa_client.transports.grpcio import GrpcTransport
from esa_client.transports.native import NativeGrpcTransport


def sibling(name: str) -> ModuleType:
    """Another test module of this folder (``--import-mode=importlib`` keeps it off sys.path)."""
    spec = importlib.util.spec_from_file_location(
        f"_native_grpc_{name}", Path(__file__).with_name(f"{name}.py")
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_parity = sibling("test_inprocess")
# Collected here too, with this module's ``local``: the native client of another server.
test_unary_scripts_are_identical = _parity.test_unary_scripts_are_identical
test_batch_scripts_are_identical = _parity.test_batch_scripts_are_identical
test_bad_inputs_raise_alike_and_change_nothing = (
    _parity.test_bad_inputs_raise_alike_and_change_nothing
)
CONFIG = _parity.CONFIG
freeze = sibling("test_lifecycle").freeze
TOKEN = "native-s3cret-" + "z" * 16


@pytest.fixture(scope="module")
def local(server_bin):
    """A second private server on a Unix socket, through the native client."""
    with EsaClient.spawn(server_bin, transport="native") as c:
        yield c


def step_pair(client: EsaClient) -> np.ndarray:
    """A batch's probe and report through ``client``; returns the improved actions."""
    batch = client.create_batch(CONFIG, 2)
    probes = batch.probe(np.zeros((2, 2)), [True, True])
    improved = batch.report(-np.sum(probes**2, axis=1))
    batch.close()
    assert improved is not None
    return improved


def test_the_factories_choose_the_transport(local, client):
    assert isinstance(local.transport, NativeGrpcTransport) and local.healthy()
    assert local.address.startswith("unix:")
    with pytest.raises(AttributeError, match="native"):
        local.stub  # noqa: B018 (the property raises)
    with pytest.raises(ValueError, match="tls"):
        EsaClient.connect("127.0.0.1:1", transport="native", tls=object())  # type: ignore[arg-type]
    assert not isinstance(client.transport, NativeGrpcTransport)
    with EsaClient.connect(local.address, transport="native", wait_ready=True) as native:
        assert isinstance(native.transport, NativeGrpcTransport)
        assert (step_pair(native) == step_pair(local)).all()
    with EsaClient.connect(local.address) as grpcio:
        assert isinstance(grpcio.transport, GrpcTransport) and grpcio.healthy()


def test_the_deprecated_constructors_still_work(local):
    """``EsaClient(address, native=...)`` and ``spawn(native=True)``: aliases for one release."""
    with EsaClient(local.address, native=True) as native:
        assert isinstance(native.transport, NativeGrpcTransport) and native.healthy()
    with EsaClient(local.address) as grpcio:
        assert isinstance(grpcio.transport, GrpcTransport) and grpcio.healthy()


@pytest.mark.parametrize(
    ("arguments", "match"),
    [
        ({"transport": "pigeon"}, "transport"),
        ({"shards": 2}, "shards with transport='zenoh' only"),
        ({"prefix": "esa/v1", "transport": "native"}, "prefix with transport='zenoh' only"),
        ({"transport": "zenoh", "tls": object()}, "tls=None with transport='zenoh'"),
    ],
)
def test_connect_refuses_arguments_its_transport_does_not_take(arguments, match):
    with pytest.raises(ValueError, match=match):
        EsaClient.connect("127.0.0.1:1", **arguments)


def test_tcp_and_the_auth_token(server_bin, serve_tcp, tmp_path):
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN)
    with serve_tcp(server_bin, "--auth-token-file", str(token_file)) as address:
        with EsaClient.connect(address, transport="native", token=TOKEN) as owner:
            assert owner.healthy(wait_for_ready=True)
            with EsaClient(address, token=TOKEN) as grpcio:
                assert (step_pair(owner) == step_pair(grpcio)).all()
        for token in (None, "wrong"):
            with EsaClient(address, native=True, token=token) as stranger:
                assert stranger.healthy()  # health needs no token
                with pytest.raises(Unauthenticated) as info:
                    stranger.create_session(CONFIG)
                assert info.value.code == StatusCode.UNAUTHENTICATED


def test_a_dead_server_is_unavailable(server_bin, monkeypatch):
    monkeypatch.delenv("ESA_AUTH_TOKEN", raising=False)
    with EsaClient("unix:/nonexistent/esa.sock", native=True, timeout=2) as nobody:
        assert not nobody.healthy(timeout=0.2, wait_for_ready=True)
        with pytest.raises(ServerUnavailable) as info:
            nobody.create_session(CONFIG)
        assert info.value.code == StatusCode.UNAVAILABLE
    with EsaClient.spawn(server_bin, native=True, reconnect_timeout=0) as client:
        batch = client.create_batch(CONFIG, 2)
        batch.probe(np.zeros((2, 2)), [True, True])
        assert client.server is not None
        client.server.stop()
        with pytest.raises(ServerUnavailable):
            batch.report([1.0, 2.0])


def test_a_frozen_server_hits_the_deadline(server_bin):
    with EsaClient.spawn(server_bin, native=True, timeout=0.5) as client:
        session = client.create_session(CONFIG)
        assert client.server is not None
        freeze(client.server.pid)
        try:
            with pytest.raises(DeadlineExceeded) as info:
                session.probe([0.0, 0.0], episode_start=True)
            assert info.value.code == StatusCode.DEADLINE_EXCEEDED
        finally:
            os.kill(client.server.pid, signal.SIGCONT)
        assert session.probe([0.0, 0.0], episode_start=True).shape == (2,)


def test_an_idle_connection_answers_the_servers_pings(server_bin):
    # The server closes a connection whose ping goes unanswered for 2.5 s; no call runs here.
    keepalive = ["--keepalive-interval", "0.3", "--keepalive-timeout", "2.5"]
    with EsaClient.spawn(server_bin, native=True, extra_args=keepalive) as client:
        batch = client.create_batch(CONFIG, 2)
        batch.probe(np.zeros((2, 2)), [True, True])
        time.sleep(3.5)
        assert batch.report([1.0, 2.0]).shape == (2, 2)
        assert client.server is not None
        assert "closed" not in client.server.output_tail().lower()


def test_a_closed_client_is_unavailable(server_bin, local):
    with EsaClient(local.address, native=True) as other:
        batch = other.create_batch(CONFIG, 1, ids=[f"closed-{uuid.uuid4()}"])
    with pytest.raises(ServerUnavailable, match="closed"):
        batch.probe(np.zeros((1, 2)))
    with pytest.raises(SessionNotFound):
        local.session_state("ghost")


def test_addresses_are_checked():
    for address in ("localhost", "unix:", "host:port"):
        with pytest.raises(ValueError):
            EsaClient(address, native=True)
    with pytest.raises(ValueError, match="timeout"):
        NativeGrpcTransport("127.0.0.1:1", float("inf"))

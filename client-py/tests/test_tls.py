"""EsaClient over TLS to a real esa-server on 127.0.0.1 (``--tls-cert``/``--tls-key``, and
``--tls-client-ca`` for mutual TLS): served with the right CA (and client certificate), and
the client's own exceptions otherwise (the gRPC transport is the extension's Rust client).

The certificates are fixed test-only files (fixtures/tls/README.md)."""

import json
from pathlib import Path

import numpy as np
import pytest

from esa_client import (
    EsaClient,
    EsaError,
    ServerUnavailable,
    SessionConfig,
    StatusCode,
    TlsConfig,
    Unauthenticated,
)

PKI = Path(__file__).resolve().parent / "fixtures" / "tls"
CONFIG = SessionConfig(action_dim=2, dt=0.05, amplitude=0.2, frequency=10.0, learning_rate=0.5)
TOKEN = "tls-s3cret-" + "y" * 16
TRUSTING = TlsConfig(ca=PKI / "ca.pem")
TRAINER = TlsConfig(ca=PKI / "ca.pem", cert=PKI / "client.pem", key=PKI / "client-key.pem")


TLS_ARGS = ("--tls-cert", str(PKI / "server.pem"), "--tls-key", str(PKI / "server-key.pem"))


@pytest.fixture(scope="module")
def tls_server(server_bin, serve_tcp):
    """esa-server over TLS on a free loopback port; yields its address."""
    with serve_tcp(server_bin, *TLS_ARGS) as address:
        yield address


@pytest.fixture(scope="module")
def mutual_server(server_bin, serve_tcp, tmp_path_factory):
    """Mutual TLS and a token, the setup for a server reachable beyond its host."""
    token_file = tmp_path_factory.mktemp("token") / "token"
    token_file.write_text(TOKEN)
    token_file.chmod(0o600)
    client_ca = ("--tls-client-ca", str(PKI / "ca.pem"), "--auth-token-file", str(token_file))
    with serve_tcp(server_bin, *TLS_ARGS, *client_ca) as address:
        yield address


def probe_and_report(client: EsaClient, use_stream: bool) -> None:
    session = client.create_session(CONFIG)
    probe = session.probe([0.1, -0.2], episode_start=True)
    assert session.report(q_value=float(np.sum(probe))).shape == (2,)
    batch = client.create_batch(CONFIG, 3, use_stream=use_stream)
    probes = batch.probe(np.zeros((3, 2)), [True] * 3)
    assert batch.report(probes.sum(axis=1)).shape == (3, 2)
    batch.close()
    session.close()


@pytest.mark.parametrize("use_stream", [False, True], ids=["unary", "stream"])
def test_a_client_trusting_the_ca_is_served(tls_server, use_stream):
    with EsaClient.connect(tls_server, tls=TRUSTING) as client:
        assert client.healthy()
        probe_and_report(client, use_stream)
    # The certificate names localhost too.
    port = tls_server.rpartition(":")[2]
    with EsaClient.connect(f"localhost:{port}", tls=TRUSTING) as client:
        client.create_session(CONFIG).close()


@pytest.mark.parametrize(
    "tls",
    [TlsConfig(ca=PKI / "other-ca.pem"), None],
    ids=["wrong-ca", "plaintext"],
)
def test_clients_that_cannot_speak_tls_with_it_get_the_clients_own_error(tls_server, tls):
    with pytest.raises(ServerUnavailable, match="over TLS, the CA and server name"):
        EsaClient.connect(tls_server, tls=tls, timeout=3.0)
    with EsaClient.connect(tls_server, tls=tls, timeout=3.0, check=False) as client:
        assert not client.healthy(timeout=2.0)
        with pytest.raises(ServerUnavailable) as info:
            client.create_session(CONFIG)
    assert isinstance(info.value, EsaError)
    assert info.value.code == StatusCode.UNAVAILABLE


def test_a_wrong_server_name_is_refused(tls_server):
    wrong_name = TlsConfig(ca=PKI / "ca.pem", server_name="esa.example")
    with pytest.raises(ServerUnavailable):
        EsaClient.connect(tls_server, tls=wrong_name, timeout=3.0)


@pytest.mark.parametrize("use_stream", [False, True], ids=["unary", "stream"])
def test_mutual_tls_with_a_token_serves_the_trainer(mutual_server, use_stream):
    with EsaClient.connect(mutual_server, tls=TRAINER, token=TOKEN) as client:
        probe_and_report(client, use_stream)


def test_mutual_tls_refuses_clients_without_the_certificate_or_token(mutual_server):
    with pytest.raises(Unauthenticated):
        EsaClient.connect(mutual_server, tls=TRAINER, timeout=3.0)
    stranger = TlsConfig(ca=PKI / "ca.pem", cert=PKI / "stranger.pem", key=PKI / "stranger-key.pem")
    for tls in (TRUSTING, stranger):
        with pytest.raises(ServerUnavailable):
            EsaClient.connect(mutual_server, tls=tls, token=TOKEN, timeout=3.0)


def test_tls_settings_are_checked_when_the_client_is_made(tmp_path):
    with pytest.raises(ValueError, match="both cert and key"):
        TlsConfig(ca=PKI / "ca.pem", cert=PKI / "client.pem")
    with pytest.raises(ValueError, match="TCP only"):
        EsaClient.connect(f"unix:{tmp_path}/esa.sock", tls=TRUSTING)
    with pytest.raises(FileNotFoundError):
        EsaClient.connect("127.0.0.1:1", tls=TlsConfig(ca=tmp_path / "missing.pem"))


def test_zenoh_over_mutual_tls_admits_only_certificates_of_the_ca(server_bin, tmp_path):
    """The Python zenoh package speaks TLS too: a trainer with a certificate of the CA is
    served over a TLS-only, mutually authenticated link; one without cannot even connect."""
    zenoh = pytest.importorskip("zenoh")
    from esa_client.sidecar import ServerProcess
    from esa_client.transports.zenoh import peer_config

    server_config = tmp_path / "server-mtls.json5"
    server_config.write_text(
        json.dumps(
            {
                "mode": "peer",
                "listen": {"endpoints": ["tls/127.0.0.1:0"]},
                "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
                "transport": {
                    "link": {
                        "tls": {
                            "root_ca_certificate": str(PKI / "ca.pem"),
                            "listen_certificate": str(PKI / "server.pem"),
                            "listen_private_key": str(PKI / "server-key.pem"),
                            "enable_mtls": True,
                        }
                    }
                },
            }
        )
    )
    server = ServerProcess(server_bin, extra_args=["--zenoh", "--zenoh-config", str(server_config)])
    try:
        locators = server.announced("zenoh listening on ", 15.0)
        assert locators and all(loc.startswith("tls/127.0.0.1:") for loc in locators)

        def trainer_config(cert: str | None) -> zenoh.Config:
            # Zenoh retries a refused link until this connect timeout: short for outsiders.
            config = peer_config(locators, 5.0 if cert == "client" else 1.0)
            tls = {"root_ca_certificate": str(PKI / "ca.pem")}
            if cert is not None:
                tls |= {
                    "connect_certificate": str(PKI / f"{cert}.pem"),
                    "connect_private_key": str(PKI / f"{cert}-key.pem"),
                    "enable_mtls": True,
                }
            config.insert_json5("transport/link/tls", json.dumps(tls))
            return config

        with EsaClient.connect(
            locators, transport="zenoh", zenoh_config=trainer_config("client")
        ) as trainer:
            session = trainer.create_session(CONFIG)
            session.probe([0.1, -0.2], episode_start=True)
            assert session.report(q_value=0.5).shape == (2,)
        for outsider in ("stranger", None):
            with pytest.raises(ServerUnavailable):
                EsaClient.connect(
                    locators, transport="zenoh", zenoh_config=trainer_config(outsider), timeout=3.0
                )
    finally:
        server.stop()

"""The Python client against an esa-server started by hand on loopback TCP (port 0)."""

import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from esa_client import EsaClient, EsaError, SessionConfig
from esa_client.sidecar import find_server_binary

REPO_ROOT = Path(__file__).resolve().parents[1]


def serving(argv: list[str]) -> Iterator[str]:
    """Runs a server that prints ``listening on ADDR`` once bound; yields ADDR, then stops it.

    Yields:
        The address; connecting right after works.
    """
    process = subprocess.Popen(
        argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    )
    try:
        line = process.stdout.readline()
        assert line.startswith("listening on "), line
        yield line.split()[-1]
    finally:
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=10) == 0


@pytest.fixture
def tcp_server():
    # The client's own lookup: ESA_SERVER_BIN (`make test`), an installed esa-server
    # wheel, or this checkout's target/release/esa-server (never built here).
    try:
        binary = str(find_server_binary(checkout=REPO_ROOT, build=False))
    except EsaError as err:
        pytest.fail(str(err))
    yield from serving([binary, "--listen", "127.0.0.1:0"])


def test_client_over_tcp_matches_reference(tcp_server):
    config = SessionConfig(
        action_dim=2, dt=0.04, amplitude=0.2, frequency=[31.4, 15.7], learning_rate=0.3
    )
    rng = np.random.default_rng(0)
    with (
        EsaClient.connect(tcp_server, timeout=5.0) as client,
        EsaClient.in_process() as engine,
    ):
        batch = client.create_batch(config, 4, use_stream=True)
        reference = engine.create_batch(config, 4)  # esa-core in-process: the baseline
        for t in range(50):
            actions = rng.normal(size=(4, 2))
            starts = np.full(4, t == 0)
            probes = batch.probe(actions, starts)
            np.testing.assert_allclose(
                probes, reference.probe(actions, starts), rtol=1e-9
            )
            q = -np.tanh(np.sum(probes**2, axis=1))
            np.testing.assert_allclose(batch.report(q), reference.report(q), rtol=1e-9)
        batch.close()


@pytest.fixture
def grpcio_server():
    """A grpcio server whose StepStream sends its headers only with its first answer."""
    yield from serving(
        [sys.executable, str(REPO_ROOT / "tests/late_headers_server.py")]
    )


def test_step_stream_opens_on_a_server_that_answers_headers_late(grpcio_server):
    config = SessionConfig(
        action_dim=2, dt=0.04, amplitude=0.2, frequency=[31.4, 15.7], learning_rate=0.3
    )
    with (
        # check=False: this server serves EsaService alone, without gRPC health.
        EsaClient.connect(grpcio_server, timeout=5.0, check=False) as client,
        EsaClient.in_process() as engine,
    ):
        batch = client.create_batch(config, 4, use_stream=True)
        reference = engine.create_batch(config, 4)
        actions, starts = np.ones((4, 2)), np.ones(4, bool)
        # The stream opens without waiting for the headers (which would hit the deadline).
        np.testing.assert_allclose(
            batch.probe(actions, starts), reference.probe(actions, starts)
        )
        batch.close()

"""Fixtures: the real esa-server binary, a shared spawned server, and config generators."""

import importlib.util
import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from esa_client import EsaClient, EsaError, SessionConfig
from esa_client.sidecar import find_server_binary

REPO_ROOT = Path(__file__).resolve().parents[2]


def _load_helper(name: str) -> None:
    """Makes ``import <name>`` work in the test modules for a helper module of this folder.

    ``--import-mode=importlib`` keeps this folder off ``sys.path``, so the module is
    loaded here, once, before any test module is imported.
    """
    if name in sys.modules:
        return
    spec = importlib.util.spec_from_file_location(name, Path(__file__).with_name(f"{name}.py"))
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)


# reference_law: the law in numpy; raw_grpc: a grpcio peer for raw requests.
for _helper in ("reference_law", "raw_grpc"):
    _load_helper(_helper)


@pytest.fixture(scope="session")
def server_bin() -> str:
    """The esa-server executable, found as the client finds it (``find_server_binary``).

    ``make test`` exports ESA_SERVER_BIN as the binary it built, which wins; otherwise the
    installed esa-server wheel, else this checkout's target/release/esa-server (never
    built here: a test run does not start a cargo build).
    """
    try:
        return str(find_server_binary(checkout=REPO_ROOT, build=False))
    except EsaError as err:
        pytest.fail(str(err))


@pytest.fixture(scope="session")
def client(server_bin):
    """One private server for the whole session; tests use unique session ids."""
    with EsaClient.spawn(server_bin) as c:
        yield c


@contextmanager
def tcp_server(server_bin: str, *args: str) -> Iterator[str]:
    """esa-server on a free loopback port with ``args``, stopped on exit; yields its address."""
    server = subprocess.Popen(
        # Dies with this test process, whatever ends it.
        [server_bin, "--listen", "127.0.0.1:0", "--parent-pid", str(os.getpid()), *args],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        assert server.stdout is not None
        address = next(
            (
                line.removeprefix("listening on ").strip()
                for line in server.stdout
                if line.startswith("listening on ")
            ),
            None,
        )
        if address is None:
            server.wait(timeout=10)
            pytest.fail(f"esa-server exited ({server.returncode}) without listening")
        yield address
    finally:
        server.terminate()
        try:
            server.wait(timeout=10)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()


@pytest.fixture(scope="session")
def serve_tcp():
    """:func:`tcp_server`: ``with serve_tcp(server_bin, *args) as address``."""
    return tcp_server


def random_config(rng: np.random.Generator, action_dim: int | None = None) -> SessionConfig:
    """A random valid config exercising every optional field, CONTRACT.md section 1b included."""
    d = int(action_dim if action_dim is not None else rng.integers(1, 5))
    dt = float(rng.choice([0.002, 0.01, 0.04, 0.05]))

    def vec(low, high):
        return rng.uniform(low, high) if rng.random() < 0.5 else rng.uniform(low, high, size=d)

    bounded = rng.random() < 0.6
    return SessionConfig(
        action_dim=d,
        dt=dt,
        amplitude=vec(0.0, 0.5),
        frequency=np.minimum(vec(1.0, 40.0), 0.99 * np.pi / dt),
        learning_rate=vec(0.0, 2.0),
        highpass_cutoff=float(rng.uniform(0.1, 5.0)) if rng.random() < 0.5 else None,
        disable_highpass=bool(rng.random() < 0.3),
        action_low=-rng.uniform(0.5, 2.0, size=d) if bounded else None,
        action_high=rng.uniform(0.5, 2.0, size=d) if bounded else None,
        shift_limit=float(rng.uniform(0.05, 1.0)) if rng.random() < 0.5 else None,
        lr_decay=float(rng.uniform(0.5, 1.0)) if rng.random() < 0.5 else None,
        max_episodes=int(rng.integers(0, 4)),
        normalize_response=bool(rng.random() < 0.5),
        response_rms_rate=float(rng.uniform(0.01, 1.0)) if rng.random() < 0.5 else None,
        response_clip=float(rng.uniform(0.5, 5.0)) if rng.random() < 0.5 else None,
        shift_leak=float(rng.uniform(0.0, 0.2)) if rng.random() < 0.5 else None,
        trust_region=float(rng.uniform(0.1, 3.0)) if rng.random() < 0.5 else None,
    )


@pytest.fixture
def make_config():
    """Factory for random valid configs (seeded by the caller)."""
    return random_config


def same_states(server_states, reference_states) -> None:
    """Asserts that sessions' states (server vs ``reference_law``) agree to 1e-9."""
    tol = dict(rtol=1e-9, atol=1e-9)
    for got, want in zip(server_states, reference_states, strict=True):
        assert got.config == want.config
        assert (got.step, got.episodes_completed, got.probe_pending) == (
            want.step,
            want.episodes_completed,
            want.probe_pending,
        )
        np.testing.assert_allclose(got.shift, want.shift, **tol)
        if want.response_mean_square is None:
            assert got.response_mean_square is None
        else:
            np.testing.assert_allclose(got.response_mean_square, want.response_mean_square, **tol)


@pytest.fixture
def assert_same_states():
    """:func:`same_states`, for the parity tests of every transport."""
    return same_states


@pytest.fixture(scope="session")
def zenoh_client(server_bin):
    """One private server with Zenoh on loopback (and gRPC on a Unix socket), over Zenoh."""
    with EsaClient.spawn(server_bin, transport="zenoh") as c:
        yield c


@pytest.fixture(scope="session")
def zenoh_grpc_client(zenoh_client):
    """A gRPC client of the same server as ``zenoh_client``: same sessions, other transport."""
    server = zenoh_client.server
    with EsaClient.connect(server.address, token=server.token) as c:
        yield c

"""The RLlib node sidecar (esa_client.rllib.service): one server per node, however runners race.

Plain processes stand in for EnvRunners (the module needs no Ray): several start at the
same instant and must get one server; it outlives the runner that started it, stops
once the last one has gone, and a killed sidecar is replaced by the next runner.
"""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from esa_client import EsaClient
from esa_client.errors import EsaError
from esa_client.rllib.service import EsaService, NodeSidecar, _alive
from esa_client.transports.grpc import GrpcTransport

RUNNER = """
import json, sys, time
from esa_client.rllib.service import NodeSidecar
directory, start_at, hold = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
time.sleep(max(0.0, start_at - time.time()))
sidecar = NodeSidecar(directory)
print(json.dumps({"address": sidecar.address, "started": sidecar.started}), flush=True)
time.sleep(hold)
"""


@pytest.fixture
def sidecar_dir(tmp_path, server_bin, monkeypatch):
    monkeypatch.setenv("ESA_SERVER_BIN", server_bin)
    directory = tmp_path / "sidecar"
    yield directory
    # Never leave a sidecar behind, whatever the test did.
    info = directory / "server.json"
    if info.exists():
        os.kill(json.loads(info.read_text())["keeper_pid"], signal.SIGTERM)


def stopped(directory, timeout=15.0):
    """True once every sidecar started in ``directory`` has stopped and said so."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        log = (directory / "keeper.log").read_text()
        done = log.count("serving ") == log.count("no runner left: stopped")
        if done and not (directory / "server.json").exists():
            return True
        time.sleep(0.05)
    return False


def runners(directory, count, hold):
    start_at = time.time() + 1.5  # after every interpreter has imported esa_client
    return [
        subprocess.Popen(
            [sys.executable, "-c", RUNNER, str(directory), str(start_at), str(hold)],
            stdout=subprocess.PIPE,
            text=True,
        )
        for _ in range(count)
    ]


def test_runners_starting_at_once_share_one_sidecar_which_stops_after_the_last(sidecar_dir):
    processes = runners(sidecar_dir, 4, hold=1.5)
    joined = [json.loads(p.stdout.readline()) for p in processes]
    assert len({j["address"] for j in joined}) == 1
    assert sum(j["started"] for j in joined) == 1
    # One more user: the same server, healthy, now shared with this process.
    mine = NodeSidecar(sidecar_dir)
    assert not mine.started and mine.address == joined[0]["address"]
    for p in processes:
        assert p.wait(timeout=30) == 0
    with EsaClient.connect(mine.address) as client:
        client.wait_ready(5.0)  # still up: this process holds it
    assert (sidecar_dir / "server.json").exists()
    mine.release()
    assert stopped(sidecar_dir)
    log = (sidecar_dir / "keeper.log").read_text()
    assert log.count("serving ") == 1 and "no runner left: stopped" in log
    assert oct(sidecar_dir.stat().st_mode & 0o777) == "0o700"


def test_a_killed_sidecar_is_replaced_by_the_next_runner(sidecar_dir):
    first = NodeSidecar(sidecar_dir)
    assert first.started
    keeper = json.loads((sidecar_dir / "server.json").read_text())["keeper_pid"]
    os.kill(keeper, signal.SIGKILL)  # the server follows it (--parent-pid)
    deadline = time.monotonic() + 10
    while _alive(keeper) and time.monotonic() < deadline:
        time.sleep(0.01)
    second = NodeSidecar(sidecar_dir)
    assert second.started and second.address != first.address
    successor = json.loads((sidecar_dir / "server.json").read_text())["keeper_pid"]
    with EsaClient.connect(second.address) as client:
        client.wait_ready(5.0)
    first.release()
    second.release()
    # The killed keeper never said it stopped; its successor must, once both let go.
    deadline = time.monotonic() + 15
    while _alive(successor) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(successor)
    assert not (sidecar_dir / "server.json").exists()
    assert (sidecar_dir / "keeper.log").read_text().count("no runner left: stopped") == 1


def test_the_sidecar_directory_must_be_private(tmp_path):
    shared = tmp_path / "shared"
    shared.mkdir(mode=0o755)
    shared.chmod(0o755)
    with pytest.raises(EsaError, match="0700"):
        NodeSidecar(shared)


def test_service_settings_are_checked():
    with pytest.raises(ValueError, match="address or zenoh"):
        EsaService(address="127.0.0.1:50051", zenoh="tcp/127.0.0.1:7447")
    with pytest.raises(ValueError, match="shards"):
        EsaService(address="127.0.0.1:50051", shards=2)
    with pytest.raises(ValueError, match="timeout"):
        EsaService(timeout=0)
    with pytest.raises(ValueError, match="on_unavailable"):
        EsaService(on_unavailable="retry")
    assert EsaService().uses_sidecar
    assert not EsaService(zenoh=["tcp/127.0.0.1:7447"], shards=2).uses_sidecar


def test_runners_follow_a_sidecar_killed_mid_training(sidecar_dir):
    import threading

    import numpy as np

    from esa_client import SessionConfig

    config = SessionConfig(
        action_dim=2, dt=0.02, amplitude=0.2, frequency=[31.4, 15.7], learning_rate=0.05
    )
    service = EsaService(sidecar_dir=str(sidecar_dir), timeout=1.0, reconnect_timeout=20)
    clients = [service.connect() for _ in range(2)]
    # The runners reach their sidecar through the Rust client, its batches on a StepStream.
    assert all(isinstance(c.transport.client.transport, GrpcTransport) for c in clients)
    batches = [c.create_batch(config, 2, use_stream=True) for c in clients]
    errors, steps = [], 250

    def train(batch, seed):
        rng = np.random.default_rng(seed)
        try:
            for t in range(steps):
                probes, applied = batch.probe_applied(rng.normal(size=(2, 2)), [t % 40 == 0] * 2)
                batch.report(-np.sum(probes**2, axis=1), defer=True)
                time.sleep(0.004)
            batch.flush()
        except BaseException as err:  # noqa: BLE001 (reported below)
            errors.append(err)

    threads = [threading.Thread(target=train, args=(b, i)) for i, b in enumerate(batches)]
    for thread in threads:
        thread.start()
    time.sleep(0.4)
    server = json.loads((sidecar_dir / "server.json").read_text())["server_pid"]
    os.kill(server, signal.SIGKILL)  # its keeper exits; a runner starts the next one
    for thread in threads:
        thread.join(timeout=30)
        assert not thread.is_alive(), "a runner hangs"
    assert errors == []
    for client, batch in zip(clients, batches, strict=True):
        assert batch.sessions_restored == 2
        assert [s.step for s in batch.states()] == batch.steps.tolist()
        assert client.transport.generation == 1
    addresses = {c.transport.sidecar.address for c in clients}
    assert len(addresses) == 1  # both follow the one new sidecar
    assert {c.address for c in clients} == addresses
    successor = json.loads((sidecar_dir / "server.json").read_text())["keeper_pid"]
    for client in clients:
        client.close()
    deadline = time.monotonic() + 15  # the new sidecar stops once both let go
    while _alive(successor) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(successor)
    assert not (sidecar_dir / "server.json").exists()

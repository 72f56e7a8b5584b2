"""What a user of the esa wheels does, in a venv that holds only the wheels and their deps.

``wheel_check.py`` copies this file into a temporary directory and runs it there with the
clean venv's interpreter in isolated mode (``-I``), without cargo on PATH, without
``ESA_SERVER_BIN`` and outside the checkout, twice. Each time it checks that nothing comes
from the checkout, then uses the wheels as a user would:

``client`` (``pip install "esa-client[sb3]"``, no server wheel):
  1. no esa-server is found, and ``EsaClient.spawn()`` says how to get one;
  2. a ``SessionBatch`` of the in-process engine, equal bit for bit, step for step, to the
     extension's ``Engine`` driven with the same inputs.

``server`` (the same venv after ``pip install "esa-client[sb3,server]"``):
  1. the esa-server wheel's executable is the one found, in the venv's ``bin/``, at the
     client's version (``python -m esa_server --version``);
  2. ``EsaClient.spawn()`` starts it, and its ``SessionBatch`` equals the ``Engine`` bit for
     bit, step for step; the server stops with its client;
  3. a few hundred ``ESAPPO`` and ``ESASAC`` steps on Pendulum-v1 (gymnasium, no MuJoCo) on
     the in-process and the sidecar engine, with the ESA statistics logged and finite.

Usage: python -I wheel_user_check.py {client,server} CHECKOUT OUT_JSON
(CHECKOUT: the repository the wheels were built from, which must stay invisible.)
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

STAGE = sys.argv[1]
CHECKOUT = Path(sys.argv[2]).resolve()
OUT = Path(sys.argv[3])
timings: dict[str, float] = {}


@contextmanager
def phase(name: str) -> Iterator[None]:
    print(f"..  {name}", flush=True)
    start = time.perf_counter()
    yield
    timings[name] = round(time.perf_counter() - start, 2)
    print(f"ok  {name}: {timings[name]} s", flush=True)


def inside_checkout(path: str | Path) -> bool:
    resolved = Path(path or ".").resolve()
    return resolved == CHECKOUT or CHECKOUT in resolved.parents


with phase("import esa_client, numpy"):
    import numpy as np

    import esa_client
    from esa_client import EsaClient, EsaConfig, EsaError, SessionConfig
    from esa_client._native import Engine
    from esa_client.sidecar import find_server_binary

package = Path(esa_client.__file__).resolve().parent
assert not inside_checkout(package), f"esa_client imported from the checkout: {package}"
assert "site-packages" in package.parts, f"esa_client is not an installed package: {package}"
leaks = [entry for entry in sys.path if inside_checkout(entry)]
assert not leaks, f"the checkout is on sys.path: {leaks}"
assert not inside_checkout(Path.cwd()), f"running inside the checkout: {Path.cwd()}"
for tool in ("cargo", "rustc", "esa-server"):
    found = shutil.which(tool)
    # The server wheel puts esa-server into the venv's bin/, which is on PATH here.
    in_venv = found is not None and Path(found).parent == Path(sys.prefix) / "bin"
    assert found is None or (STAGE == "server" and in_venv), f"{tool} is on PATH: {found}"
assert "ESA_SERVER_BIN" not in os.environ, "ESA_SERVER_BIN is set"
assert not any(package.rglob("esa-server*")), "the client wheel carries a server"

CONFIG = SessionConfig(
    action_dim=2,
    dt=0.04,
    amplitude=0.2,
    frequency=[31.4, 15.7],
    learning_rate=0.3,
    action_low=-1.0,
    action_high=1.0,
)


def against_engine(client: EsaClient) -> None:
    """200 steps of 4 sessions on ``client`` and in the native engine: equal bit for bit."""
    n, rng = 4, np.random.default_rng(0)
    engine = Engine()
    ids = [engine.create_session(None, CONFIG.to_proto().SerializeToString()) for _ in range(n)]
    handle = engine.resolve(ids)
    batch = client.create_batch(CONFIG, n)
    moved = 0.0
    for t in range(200):
        actions = rng.uniform(-1.0, 1.0, size=(n, 2))
        starts = np.full(n, t % 50 == 0)
        steps = np.full(n, t % 50, dtype=np.uint64)
        probes = batch.probe(actions, starts)
        native_probes, _ = engine.probe(handle, steps, actions, starts)
        np.testing.assert_array_equal(probes, native_probes)
        q = -np.sum(probes**2, axis=1)
        improved = batch.report(q)
        np.testing.assert_array_equal(improved, engine.report(handle, steps, q))
        moved = max(moved, float(np.abs(improved - actions).max()))
    assert moved > 0, "ESA never moved an action"
    batch.close()
    assert len(engine) == n


def client_stage() -> dict[str, object]:
    """The client wheel alone: no server anywhere, and the errors say how to get one."""
    try:
        import esa_server  # noqa: F401
    except ImportError:
        pass
    else:
        raise AssertionError("esa_server is installed without the server extra")
    hint = 'pip install "esa-client[server]"'
    with phase("EsaClient.spawn() without a server says how to get one"):
        for attempt in (find_server_binary, EsaClient.spawn):
            try:
                attempt()
            except EsaError as error:
                assert hint in str(error), str(error)
                message = str(error)
            else:
                raise AssertionError(f"{attempt.__name__} found a server")
    with phase("EsaClient.in_process() SessionBatch == _native.Engine (200 steps x 4)"):
        with EsaClient.in_process() as client:
            against_engine(client)
    return {"missing_server_error": message}


def train(name: str, make_model: Callable[[], object], steps: int, **learn: object) -> dict:
    """Trains ``steps`` steps; checks where the sessions lived and the ESA statistics.

    A sidecar model must have used the server wheel's executable; an in-process one none.
    """
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.logger import configure

    class RecordServer(BaseCallback):
        binaries: set[str] = set()

        def _on_step(self) -> bool:
            runtime = self.model._esa
            if runtime is not None:
                server = runtime.client.server
                self.binaries.add(str(server.binary) if server is not None else "in-process")
            return True

    folder = Path(tempfile.mkdtemp(prefix=f"esa-wheel-{name}-"))
    model = make_model()
    model.set_logger(configure(str(folder), ["csv"]))
    record = RecordServer()
    model.learn(steps, callback=record, **learn)
    model.esa_close()
    spawned = model.esa_client.server is not None
    expected = str(find_server_binary()) if spawned else "in-process"
    assert record.binaries == {expected}, record.binaries
    with open(folder / "progress.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    shift = [float(r["esa/mean_abs_shift"]) for r in rows if r.get("esa/mean_abs_shift")]
    assert shift and np.all(np.isfinite(shift)), f"{name}: esa/mean_abs_shift {shift}"
    return {"steps": steps, "log_rows": len(rows), "last esa/mean_abs_shift": shift[-1]}


def server_stage() -> dict[str, object]:
    """With the server wheel: it is found, spawned, equal to the engine, and trains."""
    from esa_server import find_esa_server_bin

    installed = find_esa_server_bin()
    assert installed.parent == Path(sys.prefix) / "bin", f"not in the venv's bin/: {installed}"
    assert find_server_binary() == installed, find_server_binary()
    version = subprocess.run(
        [sys.executable, "-m", "esa_server", "--version"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.split()
    assert version == ["esa-server", esa_client.__version__], version

    with phase("EsaClient.spawn() SessionBatch == _native.Engine (200 steps x 4)"):
        with EsaClient.spawn() as client:
            assert client.server.binary == installed, client.server.binary
            against_engine(client)
            server_pid = client.server.pid
    try:
        os.kill(server_pid, 0)
        raise AssertionError(f"the sidecar {server_pid} outlived its client")
    except ProcessLookupError:
        pass

    with phase("import esa_client.sb3 (torch, stable-baselines3)"):
        from esa_client.sb3 import ESAPPO, ESASAC

    training = {}
    for engine in ("in-process", "spawn"):
        with phase(f"ESAPPO [{engine}] Pendulum-v1 512 steps"):
            training[f"ESAPPO [{engine}]"] = train(
                f"ppo-{engine}",
                lambda engine=engine: ESAPPO(
                    "MlpPolicy",
                    "Pendulum-v1",
                    esa=EsaConfig(gate=None),
                    esa_client=engine,
                    n_steps=128,
                    batch_size=64,
                    n_epochs=2,
                    seed=0,
                    device="cpu",
                ),
                512,
            )
    with phase("ESASAC [spawn] Pendulum-v1 400 steps"):
        training["ESASAC [spawn]"] = train(
            "sac",
            lambda: ESASAC(
                "MlpPolicy",
                "Pendulum-v1",
                esa=EsaConfig(gate=None),
                esa_client="spawn",
                learning_starts=100,
                batch_size=64,
                seed=0,
                device="cpu",
            ),
            400,
            log_interval=1,
        )
    return {"server": str(installed), "training": training}


stages = {"client": client_stage, "server": server_stage}
summary = {
    "stage": STAGE,
    "python": sys.version.split()[0],
    "esa_client": str(package),
    **stages[STAGE](),
    "timings_s": timings,
}
OUT.write_text(json.dumps(summary, indent=2))
print(json.dumps(summary, indent=2))

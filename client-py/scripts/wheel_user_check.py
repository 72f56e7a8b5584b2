"""What a user of the esa-client wheel does, in a venv that holds only the wheel and its deps.

``wheel_check.py`` copies this file into a temporary directory and runs it there with the
clean venv's interpreter in isolated mode (``-I``), without cargo on PATH, without
``ESA_SERVER_BIN`` and outside the checkout. It checks that nothing comes from the
checkout, then uses the wheel as a user would:

1. ``EsaClient.spawn()``: the sidecar must be the esa-server bundled in the wheel;
2. a ``SessionBatch`` probe/report loop, equal bit for bit, step for step, to the in-process
   engine ``esa_client._native.Engine`` driven with the same inputs;
3. a few hundred ``ESAPPO`` and ``ESASAC`` steps on Pendulum-v1 (gymnasium, no MuJoCo), each
   with its own private server (the bundled one), with the ESA statistics logged and finite.

Usage: python -I wheel_user_check.py CHECKOUT OUT_JSON
(CHECKOUT: the repository the wheel was built from, which must stay invisible.)
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

CHECKOUT = Path(sys.argv[1]).resolve()
OUT = Path(sys.argv[2])
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
    from esa_client import EsaClient, EsaConfig, SessionConfig
    from esa_client._native import Engine
    from esa_client.sidecar import bundled_server_binary, find_server_binary

package = Path(esa_client.__file__).resolve().parent
assert not inside_checkout(package), f"esa_client imported from the checkout: {package}"
assert "site-packages" in package.parts, f"esa_client is not an installed package: {package}"
leaks = [entry for entry in sys.path if inside_checkout(entry)]
assert not leaks, f"the checkout is on sys.path: {leaks}"
assert not inside_checkout(Path.cwd()), f"running inside the checkout: {Path.cwd()}"
for tool in ("cargo", "rustc", "esa-server"):
    assert shutil.which(tool) is None, f"{tool} is on PATH: {shutil.which(tool)}"
assert "ESA_SERVER_BIN" not in os.environ, "ESA_SERVER_BIN is set"
bundled = bundled_server_binary()
assert bundled == package / "_bin" / "esa-server", f"no bundled server: {bundled}"
assert find_server_binary() == bundled, find_server_binary()


def sidecar_against_engine() -> int:
    """200 steps of 4 sessions on the spawned server and in the native engine; their pid."""
    config = SessionConfig(
        action_dim=2,
        dt=0.04,
        amplitude=0.2,
        frequency=[31.4, 15.7],
        learning_rate=0.3,
        action_low=-1.0,
        action_high=1.0,
    )
    n, rng = 4, np.random.default_rng(0)
    engine = Engine()
    ids = [engine.create_session(None, config.to_proto().SerializeToString()) for _ in range(n)]
    handle = engine.resolve(ids)
    with EsaClient.spawn() as client:
        assert client.server.binary == bundled, client.server.binary
        batch = client.create_batch(config, n)
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
        return client.server.pid


def train(name: str, make_model: Callable[[], object], steps: int, **learn: object) -> dict:
    """Trains ``steps`` steps; checks where the sessions lived and the ESA statistics.

    A sidecar model must have used the bundled server; an in-process one no server at all.
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
    expected = str(bundled) if model.esa_engine == "sidecar" else "in-process"
    assert record.binaries == {expected}, record.binaries
    with open(folder / "progress.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    shift = [float(r["esa/mean_abs_shift"]) for r in rows if r.get("esa/mean_abs_shift")]
    assert shift and np.all(np.isfinite(shift)), f"{name}: esa/mean_abs_shift {shift}"
    return {"steps": steps, "log_rows": len(rows), "last esa/mean_abs_shift": shift[-1]}


with phase("EsaClient.spawn + SessionBatch == _native.Engine (200 steps x 4)"):
    server_pid = sidecar_against_engine()
try:
    os.kill(server_pid, 0)
    raise AssertionError(f"the sidecar {server_pid} outlived its client")
except ProcessLookupError:
    pass

with phase("import esa_client.sb3 (torch, stable-baselines3)"):
    from esa_client.sb3 import ESAPPO, ESASAC

training = {}
for engine in ("inprocess", "sidecar"):
    with phase(f"ESAPPO [{engine}] Pendulum-v1 512 steps"):
        training[f"ESAPPO [{engine}]"] = train(
            f"ppo-{engine}",
            lambda engine=engine: ESAPPO(
                "MlpPolicy",
                "Pendulum-v1",
                esa=EsaConfig(gate=None),
                esa_engine=engine,
                n_steps=128,
                batch_size=64,
                n_epochs=2,
                seed=0,
                device="cpu",
            ),
            512,
        )
with phase("ESASAC [sidecar] Pendulum-v1 400 steps"):
    training["ESASAC [sidecar]"] = train(
        "sac",
        lambda: ESASAC(
            "MlpPolicy",
            "Pendulum-v1",
            esa=EsaConfig(gate=None),
            esa_engine="sidecar",
            learning_starts=100,
            batch_size=64,
            seed=0,
            device="cpu",
        ),
        400,
        log_interval=1,
    )

summary = {
    "python": sys.version.split()[0],
    "esa_client": str(package),
    "bundled_server": str(bundled),
    "timings_s": timings,
    "training": training,
}
OUT.write_text(json.dumps(summary, indent=2))
print(json.dumps(summary, indent=2))

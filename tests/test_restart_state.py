"""A restart changes nothing: trainers keep their sessions across a server's stop and crash.

- SIGTERM, then a start on the same address and ``--state-file``: the trainer ends bit for bit
  where an uninterrupted run ends (the in-process engine, the same law), over gRPC (a
  StepStream, unary batches, steps sent ahead of their answers) and Zenoh, and an ESASAC
  trainer's actor is the uninterrupted run's, bit for bit.
- SIGKILL: the sessions are lost, and the client recreates them with the episode count and
  the normalization's mean square it last saw; only the running episode's shift is lost.
- A step sent ahead whose request never reached the server is sent again, and one the server
  applied is not applied twice.

Every test runs the real esa-server binary. The file's bad cases (truncated, corrupt, foreign,
newer, writable by others, expired sessions) are server/tests/api/state_file.rs.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from esa_client import EsaClient, SessionConfig
from esa_client.session import SessionBatch
from esa_client.state import SessionProgress

REPO_ROOT = Path(__file__).resolve().parents[1]

CONFIG = SessionConfig(
    action_dim=2,
    dt=0.02,
    amplitude=0.2,
    frequency=[31.4, 15.7],
    learning_rate=0.05,
    lr_decay=0.8,
    normalize_response=True,
    shift_leak=0.01,
    trust_region=1.0,
)
N = 3
EPISODE = 25
STEPS = 120
# Mid-episode, after a few episodes.
STOP_AT = 3 * EPISODE + 10
# The mean square's EMA rate when response_rms_rate is unset (CONTRACT.md section 1b).
RMS_RATE = 0.05


@pytest.fixture
def state_file(tmp_path: Path) -> Path:
    return tmp_path / "esa-state"


@pytest.fixture
def grpc_server(esa_server, state_file):
    return esa_server(state_file=state_file)


@pytest.fixture
def zenoh_server(esa_server, state_file):
    pytest.importorskip("zenoh")
    return esa_server(zenoh=True, state_file=state_file)


def _critic(points: np.ndarray) -> np.ndarray:
    """Q of ``(k N, D)`` points, not linear in the action."""
    return -np.sum((points - 0.3) ** 2, axis=1) + np.sin(3.0 * points[:, 0])


def _inputs(
    t: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step t's sampled actions, action scales and episode starts."""
    actions = rng.normal(size=(N, 2))
    scales = rng.uniform(0.2, 0.9, size=(N, 2))
    starts = np.full(N, t % EPISODE == 0)
    return actions, scales, starts


Step = Callable[[SessionBatch, np.ndarray, np.ndarray, np.ndarray], np.ndarray]


def _pipelined(batch: SessionBatch, actions, scales, starts) -> np.ndarray:
    """Algorithm 1 as the chaos trainers step it: the report rides with the next probe."""
    probes, applied = batch.probe_applied(actions, starts, action_scales=scales)
    q = _critic(np.concatenate([probes, applied]))
    batch.report(q[:N], q_references=q[N:], defer=True)
    return applied


def _whole(batch: SessionBatch, actions, scales, starts) -> np.ndarray:
    """``SessionBatch.step``: sent ahead of its answer on a gRPC StepStream."""
    return batch.step(actions, _critic, starts, action_scales=scales, paired=True)[1]


WIRES: dict[str, tuple[dict[str, object], Step]] = {
    "grpc-stream": ({"use_stream": True}, _pipelined),
    "grpc-unary": ({"use_stream": False}, _pipelined),
    "grpc-ahead": ({"use_stream": True}, _whole),
}


def _train(
    client: EsaClient,
    step: Step,
    use_stream: bool,
    chaos: Callable[[SessionBatch, int], None] = lambda batch, t: None,
) -> tuple[list[np.ndarray], SessionBatch]:
    """STEPS steps of N sessions; ``chaos(batch, t)`` runs before step t."""
    batch = client.create_batch(CONFIG, N, use_stream=use_stream)
    rng = np.random.default_rng(7)
    trajectory = []
    for t in range(STEPS):
        chaos(batch, t)
        trajectory.append(step(batch, *_inputs(t, rng)))
    batch.flush()
    return trajectory, batch


def _comparable(batch: SessionBatch) -> list[tuple[object, ...]]:
    return [
        (
            s.step,
            s.episodes_completed,
            s.probe_pending,
            s.shift.tobytes(),
            s.response_mean_square,
        )
        for s in batch.states()
    ]


def _reference(step: Step) -> tuple[list[np.ndarray], list[tuple[object, ...]]]:
    """The uninterrupted run, in-process (the server's law, bit for bit)."""
    with EsaClient.in_process() as client:
        trajectory, batch = _train(client, step, use_stream=False)
        return trajectory, _comparable(batch)


def _assert_same_run(trajectory: list[np.ndarray], expected: list[np.ndarray]) -> None:
    assert len(trajectory) == len(expected)
    for t, (got, want) in enumerate(zip(trajectory, expected, strict=True)):
        np.testing.assert_array_equal(got, want, err_msg=f"step {t}")


@pytest.mark.parametrize("wire", list(WIRES))
def test_sigterm_and_restart_continue_bit_for_bit_over_grpc(
    grpc_server, state_file, wire
):
    connect, step = WIRES[wire]
    expected, expected_states = _reference(step)
    restarts: list[threading.Thread] = []

    def chaos(batch: SessionBatch, t: int) -> None:
        if t == STOP_AT:
            grpc_server.stop()
            restarts.append(grpc_server.start_later(0.5))

    with EsaClient.connect(
        grpc_server.address, timeout=1.0, reconnect_timeout=20
    ) as client:
        trajectory, batch = _train(client, step, bool(connect["use_stream"]), chaos)
        _assert_same_run(trajectory, expected)
        assert _comparable(batch) == expected_states
        assert batch.sessions_restored == 0
    assert grpc_server.starts == 2
    assert not state_file.exists(), "a loaded state file is removed"


def test_sigterm_and_restart_continue_bit_for_bit_over_zenoh(zenoh_server):
    expected, expected_states = _reference(_pipelined)

    def chaos(batch: SessionBatch, t: int) -> None:
        if t == STOP_AT:
            zenoh_server.stop()
            zenoh_server.start_later(0.5)

    with EsaClient.connect(
        zenoh_server.address, transport="zenoh", timeout=1.0, reconnect_timeout=20
    ) as client:
        trajectory, batch = _train(client, _pipelined, True, chaos)
        _assert_same_run(trajectory, expected)
        assert _comparable(batch) == expected_states
        assert batch.sessions_restored == 0
    assert zenoh_server.starts == 2


def _sigkill_keeps_what_the_client_saw(
    server: Any, client: EsaClient, step: Step
) -> None:
    seen: list[list[SessionProgress]] = []
    checked: list[int] = []

    def chaos(batch: SessionBatch, t: int) -> None:
        if t == STOP_AT:
            batch.flush()
            progress = batch._batch.progress()
            assert progress is not None
            seen.append(progress)
            server.kill()
            server.start_later(0.5)
        elif t > STOP_AT and not checked and batch.sessions_restored:
            # The sessions came back at an episode start with what the client last saw. At
            # most the episode's first report has reached them (a pipelined report is still
            # on its way), whose response is 0: m only decays, by 1 - rho.
            assert batch.sessions_restored == N
            for session_id, progress in zip(batch.ids, seen[0], strict=True):
                state = client.transport.get_session(session_id)
                assert state.step <= 1
                assert state.episodes_completed == progress.episodes_completed == 3
                m = progress.response_mean_square
                assert m is not None
                for _ in range(state.step):
                    m = (1.0 - RMS_RATE) * m + RMS_RATE * (0.0 * 0.0)
                assert state.response_mean_square == m
            checked.append(t)

    trajectory, batch = _train(client, step, True, chaos)
    assert len(trajectory) == STEPS
    assert checked and batch.sessions_restored == N
    # The episodes that ended since count on: none was lost and none added.
    assert [s.episodes_completed for s in batch.states()] == [
        (STEPS - 1) // EPISODE
    ] * N


@pytest.mark.parametrize("wire", ["grpc-stream", "grpc-ahead"])
def test_sigkill_keeps_the_episode_count_and_mean_square_over_grpc(grpc_server, wire):
    _, step = WIRES[wire]
    with EsaClient.connect(
        grpc_server.address, timeout=1.0, reconnect_timeout=20
    ) as client:
        _sigkill_keeps_what_the_client_saw(grpc_server, client, step)


def test_sigkill_keeps_the_episode_count_and_mean_square_over_zenoh(zenoh_server):
    with EsaClient.connect(
        zenoh_server.address, transport="zenoh", timeout=1.0, reconnect_timeout=20
    ) as client:
        _sigkill_keeps_what_the_client_saw(zenoh_server, client, _pipelined)


def test_a_step_that_never_reached_the_server_is_sent_again(
    grpc_server, loopback_proxy
):
    expected, expected_states = _reference(_whole)
    proxy = loopback_proxy(grpc_server.address)

    def chaos(batch: SessionBatch, t: int) -> None:
        if t == STOP_AT:
            batch.flush()  # nothing in flight
            proxy.holding = True
        if t == STOP_AT + 1:
            # Step STOP_AT went out into the void; its answer cannot come.
            proxy.cut()

    with EsaClient.connect(proxy.address, timeout=1.0, reconnect_timeout=20) as client:
        trajectory, batch = _train(client, _whole, True, chaos)
        _assert_same_run(trajectory, expected)
        assert _comparable(batch) == expected_states
        assert batch.sessions_restored == 0


def test_esasac_stopped_and_restarted_ends_where_an_uninterrupted_run_ends(grpc_server):
    torch = pytest.importorskip("torch")
    pytest.importorskip("stable_baselines3")
    from esa_client.sb3 import ESASAC
    from stable_baselines3.common.callbacks import BaseCallback

    torch.set_num_threads(1)
    total, stop_at = 700, 350

    class Restart(BaseCallback):
        """SIGTERM at ``stop_at`` steps; the server is back 1 s later on the same address."""

        def _on_step(self) -> bool:
            if self.num_timesteps == stop_at:
                grpc_server.stop()
                grpc_server.start_later(1.0)
            return True

    def train(callback: BaseCallback | None) -> tuple[ESASAC, list[object]]:
        model = ESASAC(
            "MlpPolicy",
            "Pendulum-v1",
            esa={"gate": None, "lr_decay": 0.8},
            esa_client=EsaClient.connect(grpc_server.address, reconnect_timeout=30),
            learning_starts=100,
            batch_size=64,
            policy_kwargs={"net_arch": [32, 32]},
            seed=3,
        )
        model.learn(total, callback=callback)
        runtime = model._esa
        assert runtime is not None
        states = runtime.batch.states()
        restored = runtime.batch.sessions_restored
        model.esa_close()
        model.esa_client.close()
        return model, [states, restored]

    uninterrupted, (states, _) = train(None)
    restarted, (states_after, restored) = train(Restart())
    assert grpc_server.starts == 2
    assert restored == 0
    assert [(s.step, s.episodes_completed) for s in states_after] == [
        (s.step, s.episodes_completed) for s in states
    ]
    for (name, a), b in zip(
        uninterrupted.actor.state_dict().items(),
        restarted.actor.state_dict().values(),
        strict=True,
    ):
        assert torch.equal(a, b), f"{name}: differs by {(a - b).abs().max().item()}"

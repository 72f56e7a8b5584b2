"""ESAPPO's head fitted in the worker process: the same bits as fitting it in-process.

Real parts only: the worker is the real ``python -c ... main()`` process, the models train on
InvertedPendulum-v5.
"""

from __future__ import annotations

import copy
import logging
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest
import torch as th

from esa_client.common import head_fit_worker
from esa_client.common.advantage_head import AdvantageHead, Rollout, fit
from esa_client.common.head_fit_worker import FitJob, FitResult, HeadFitWorker, shared_worker
from esa_client.sb3 import ESAPPO, EsaConfig

READY_S = 120.0
"""Torch's import and first optimizer step in the worker, on a loaded 2-core CI machine."""
SETTINGS = dict(epochs=2, batch_size=32)


def job_parts(seed: int = 0) -> tuple[AdvantageHead, th.optim.Optimizer, list[Rollout]]:
    """A head with some Adam state, and two rollouts to fit it on."""
    th.manual_seed(seed)
    head = AdvantageHead(3, 2, hidden=8)
    optimizer = th.optim.Adam(head.parameters(), lr=1e-2, fused=True)
    rollouts = [Rollout(th.randn(50, 3), th.randn(50, 2), th.randn(50)) for _ in range(2)]
    fit(head, optimizer, rollouts[:1], rng=np.random.default_rng(1), **SETTINGS)
    return head, optimizer, rollouts


def assert_same_state(a: tuple, b: tuple) -> None:
    """Heads, optimizers and generators equal bit for bit."""
    (head_a, opt_a, rng_a), (head_b, opt_b, rng_b) = a, b
    for x, y in zip(head_a.state_dict().values(), head_b.state_dict().values(), strict=True):
        assert th.equal(x, y)
    state_a, state_b = opt_a.state_dict()["state"], opt_b.state_dict()["state"]
    assert state_a.keys() == state_b.keys()
    for key, tensors in state_a.items():
        for name, tensor in tensors.items():
            assert th.equal(tensor, state_b[key][name]), name
    assert rng_a.bit_generator.state == rng_b.bit_generator.state
    assert head_a.fits == head_b.fits


def fitted_here(head, optimizer, rollouts, rng) -> tuple[tuple, float]:
    loss = fit(head, optimizer, rollouts, rng=rng, **SETTINGS)
    return (head, optimizer, rng), loss


@pytest.fixture
def worker():
    """A worker of the test's own, started and warm."""
    started = HeadFitWorker()
    assert started.wait_ready(READY_S)
    yield started
    started.close()


def test_a_job_fits_as_fit_does():
    head, optimizer, rollouts = job_parts()
    rng = np.random.default_rng(7)
    job = FitJob.of(head, optimizer, rollouts, rng=copy.deepcopy(rng), **SETTINGS)
    result = copy.deepcopy(job).run()
    want, want_loss = fitted_here(head, optimizer, rollouts, rng)
    mine_head, mine_optimizer, _ = job_parts()
    got_rng = result.apply(mine_head, mine_optimizer)
    assert result.loss == want_loss
    assert_same_state((mine_head, mine_optimizer, got_rng), want)


def test_the_worker_gives_the_bits_of_fitting_here(worker):
    head, optimizer, rollouts = job_parts()
    rng = np.random.default_rng(7)
    pending = worker.submit(FitJob.of(head, optimizer, rollouts, rng=rng, **SETTINGS))
    assert pending is not None
    result = pending()
    assert isinstance(result, FitResult)
    # Sending the job left the trainer's state as it was.
    untouched = job_parts()
    assert_same_state((head, optimizer, rng), (*untouched[:2], np.random.default_rng(7)))
    got_rng = result.apply(head, optimizer)
    want, want_loss = fitted_here(*job_parts()[:2], rollouts, np.random.default_rng(7))
    assert result.loss == want_loss
    assert_same_state((head, optimizer, got_rng), want)


def test_a_busy_worker_leaves_the_fit_to_the_trainer(worker):
    head, optimizer, rollouts = job_parts()
    job = FitJob.of(head, optimizer, rollouts, rng=np.random.default_rng(0), **SETTINGS)
    pending = worker.submit(job)
    assert pending is not None
    assert worker.submit(job) is None
    assert pending() is not None
    assert worker.submit(job) is not None


def test_a_dead_worker_leaves_the_state_for_the_trainer(worker, caplog):
    head, optimizer, rollouts = job_parts()
    rng = np.random.default_rng(7)
    pending = worker.submit(FitJob.of(head, optimizer, rollouts, rng=rng, **SETTINGS))
    assert pending is not None
    worker._process.kill()
    with caplog.at_level(logging.WARNING):
        result = pending()
    # Killed before or after it answered: either way the trainer's state is whole.
    if result is None:
        assert "fit worker failed" in caplog.text
        assert not worker.usable
        want, _ = fitted_here(*job_parts()[:2], rollouts, np.random.default_rng(7))
        assert_same_state(fitted_here(head, optimizer, rollouts, rng)[0], want)
    again = FitJob.of(head, optimizer, rollouts, rng=rng, **SETTINGS)
    with caplog.at_level(logging.WARNING):
        assert worker.submit(again) is None
    assert not worker.usable


def test_a_job_that_fails_there_is_left_to_the_trainer(worker, caplog):
    head, optimizer, rollouts = job_parts()
    job = FitJob.of(head, optimizer, rollouts, rng=np.random.default_rng(0), **SETTINGS)
    job.sizes = (5, 2, 8)  # the head's state does not fit such a head: load_state_dict fails
    pending = worker.submit(job)
    assert pending is not None
    with caplog.at_level(logging.WARNING):
        assert pending() is None
    assert "size mismatch" in caplog.text


def test_an_interrupted_wait_retires_the_worker(worker, monkeypatch, caplog):
    # Its answer, left in the pipe, would otherwise be read as the next job's.
    head, optimizer, rollouts = job_parts()
    job = FitJob.of(head, optimizer, rollouts, rng=np.random.default_rng(0), **SETTINGS)
    pending = worker.submit(job)
    assert pending is not None

    def interrupted(*args: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(head_fit_worker, "select", SimpleNamespace(select=interrupted))
    with caplog.at_level(logging.WARNING), pytest.raises(KeyboardInterrupt):
        pending()
    assert not worker.usable
    assert worker.submit(job) is None


def test_close_ends_the_worker():
    started = HeadFitWorker()
    started.close()
    assert started._process.returncode is not None


def esappo(worker: object, **kwargs) -> ESAPPO:
    return ESAPPO(
        "MlpPolicy",
        "InvertedPendulum-v5",
        esa=EsaConfig(gate=None),
        n_steps=256,
        batch_size=64,
        n_epochs=2,
        seed=0,
        device="cpu",
        esa_head_worker=worker,
        esa_head_batch_size=64,
        **kwargs,
    )


def test_esappo_trains_the_same_bits_with_the_worker():
    shared = shared_worker(force=True)
    assert shared is not None and shared.wait_ready(READY_S)
    # One after the other: SB3 seeds torch's and numpy's global generators when it builds
    # a model, and its training draws from them.
    here = esappo(False).learn(3 * 256)
    there = esappo(True).learn(3 * 256)
    for model in (here, there):
        model.esa_close()
    assert here.logger.name_to_value["esa/head_fit_in_worker"] == 0.0
    assert there.logger.name_to_value["esa/head_fit_in_worker"] == 1.0
    assert here.esa_head.fits == there.esa_head.fits == 3
    for module in ("policy", "esa_head"):
        want, got = getattr(here, module).state_dict(), getattr(there, module).state_dict()
        for name, tensor in want.items():
            assert th.equal(tensor, got[name]), (module, name)
    assert np.array_equal(here.rollout_buffer.actions, there.rollout_buffer.actions)
    assert_same_state(
        (here.esa_head, here.esa_head_optimizer, here._esa_rng),
        (there.esa_head, there.esa_head_optimizer, there._esa_rng),
    )


def test_a_saved_model_holds_the_workers_fit(tmp_path):
    shared = shared_worker(force=True)
    assert shared is not None and shared.wait_ready(READY_S)
    model = esappo(True)
    model.learn(2 * 256)
    model.save(tmp_path / "model.zip")
    loaded = ESAPPO.load(tmp_path / "model.zip", device="cpu")
    for name, tensor in model.esa_head.state_dict().items():
        assert th.equal(tensor, loaded.esa_head.state_dict()[name])
    assert loaded.esa_head_worker is True
    for one in (model, loaded):
        one.esa_close()


@pytest.mark.parametrize("value", ["yes", 1, 0.0, None])
def test_a_bad_esa_head_worker_is_refused(value):
    with pytest.raises(ValueError, match="expected esa_head_worker True or False"):
        esappo(value)


def test_esappo_starts_no_process_by_default():
    # In a fresh interpreter: this one may hold the worker other tests started.
    script = """
import os
from esa_client.sb3 import ESAPPO

model = ESAPPO("MlpPolicy", "InvertedPendulum-v5", n_steps=64, batch_size=64, seed=0)
model.learn(3 * 64)
assert model.esa_head_worker is False
children = []
for pid in filter(str.isdigit, os.listdir("/proc")):
    try:
        with open(f"/proc/{pid}/stat") as stat:
            parent = int(stat.read().rsplit(")", 1)[1].split()[1])
    except OSError:
        continue
    if parent == os.getpid():
        children.append(pid)
print(len(children))
"""
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300, check=True
    )
    assert done.stdout.strip().splitlines()[-1] == "0", done.stdout + done.stderr

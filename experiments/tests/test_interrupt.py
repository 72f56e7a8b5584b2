"""A runner stopped mid-run ends at once, leaves no worker behind and writes no partial run."""

import contextlib
import os
import signal
import subprocess
import sys
import time

import pytest


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie waiting for init to reap it does not)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _children(pid: int) -> list[int]:
    """Direct children of ``pid`` (Linux /proc)."""
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as stat:
                    fields = stat.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                found.append(int(entry))
    return found


def _interruptible() -> None:
    """In the child before exec: SIGINT's default action, so that Python raises on it.

    A shell starts background jobs with SIGINT ignored, and Python leaves it ignored.
    """
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGKILL])
def test_stopped_runner_ends_at_once(tmp_path, signum):
    # One full-budget TD3 run: minutes of work, so it is surely in flight when stopped.
    argv = [sys.executable, "-m", "esa_experiments", "--root", str(tmp_path), "run", "seeking"]
    argv += ["--budget", "full", "--seeds", "0", "--envs", "Hopper-v5", "--methods", "td3"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "COLUMNS": "200"}
    # A session of its own, so that whatever it leaves behind can be killed with it; Ctrl-C
    # as at a terminal, although a test run in the background inherits it ignored.
    runner = subprocess.Popen(
        argv,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        preexec_fn=_interruptible,
    )
    try:
        # The resource tracker, the Manager's process and the worker; then time to import and
        # start training.
        deadline = time.monotonic() + 120
        while len(_children(runner.pid)) < 3 and time.monotonic() < deadline:
            time.sleep(0.5)
        time.sleep(10)
        assert runner.poll() is None, runner.stdout.read().decode() if runner.stdout else ""
        workers = _children(runner.pid)
        runner.send_signal(signum)
        try:
            runner.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(runner.pid, signal.SIGKILL)
            output = runner.communicate(timeout=30)[0].decode(errors="replace")
            pytest.fail(f"the runner still ran 30 s after the signal; its output:\n{output}")
        assert runner.returncode != 0
        if signum != signal.SIGKILL:
            output = runner.communicate(timeout=30)[0].decode(errors="replace")
            assert "interrupted. Finished runs are kept" in output and "Traceback" not in output
        # The workers, the Manager and the resource tracker: all gone with the runner, even
        # one killed outright (SIGKILL), which cleans up nothing itself.
        deadline = time.monotonic() + 10
        while [pid for pid in workers if _alive(pid)] and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not [pid for pid in workers if _alive(pid)]
        assert not list(tmp_path.rglob("*.json")), "a killed run must leave no result"
    finally:
        # Whatever is left of the session, so that a failure leaves no process behind.
        with contextlib.suppress(ProcessLookupError):
            os.killpg(runner.pid, signal.SIGKILL)
        runner.wait()

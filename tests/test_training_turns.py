"""The turns that bench/python/training_overhead.py's agents take while they train side by side.

The bench's ratios are only as fair as the turns: one agent runs at a time, the turn goes
round-robin to the agents still training, and each agent's clock runs during its own turns.
"""

import sys
import threading
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench" / "python"))
import training_overhead
from training_overhead import Turns


def take_turns(turns: Turns, work: dict[int, int]) -> list[int]:
    """Runs one thread per index of ``work``, each taking that many turns; returns who ran."""
    ran: list[int] = []
    running = []

    def agent(index: int) -> None:
        turns.take(index)
        for turn in range(work[index]):
            running.append(index)
            assert running == [index], "two agents ran at once"
            ran.append(index)
            time.sleep(0.002)
            running.remove(index)
            if turn < work[index] - 1:
                turns.give(index)
                turns.take(index)
        turns.give(index, done=True)

    threads = [threading.Thread(target=agent, args=(i,)) for i in work]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=10)
        assert not thread.is_alive(), "an agent waited for a turn that never came"
    return ran


def test_turns_go_round_robin_and_skip_agents_that_are_done():
    turns = Turns([0, 1, 2])
    ran = take_turns(turns, {0: 3, 1: 1, 2: 2})
    assert ran == [0, 1, 2, 0, 2, 0]
    assert all(seconds >= 0.002 for seconds in turns.seconds.values())
    # Agent 0 ran three turns, agent 1 one: each clock counts its own turns only.
    assert turns.seconds[0] > turns.seconds[1]


def test_reversed_turns_start_at_the_last_agent():
    ran = take_turns(Turns([2, 1, 0]), {0: 2, 1: 2, 2: 2})
    assert ran == [2, 1, 0, 2, 1, 0]


@pytest.mark.parametrize("value", ["0", "-0.5"])
def test_a_turn_must_last_some_time(monkeypatch, value):
    monkeypatch.setattr(sys, "argv", ["training_overhead.py", "--slice-s", value])
    with pytest.raises(
        SystemExit, match=r"expected --slice-s > 0 \(seconds per turn\), got -?0"
    ):
        training_overhead.main()

"""Riding out a lost server: retries with capped exponential backoff and jitter.

What a batch does between two attempts is :class:`~esa_client.recovery.Recovery`'s.
"""

from __future__ import annotations

import random
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

from .errors import DeadlineExceeded, EsaError, ServerUnavailable, StatusCode

__all__ = ["DEFAULT_RECONNECT_TIMEOUT", "Reconnect", "RetriableErrors", "check_reconnect_timeout"]

DEFAULT_RECONNECT_TIMEOUT = 60.0
"""How long a client keeps trying to reach a lost server before it gives up, in seconds."""

RetriableErrors = (ServerUnavailable, DeadlineExceeded)
"""The failures of the wire, not of the request: repeating the request may succeed."""

_T = TypeVar("_T")


def check_reconnect_timeout(timeout: float) -> float:
    """Returns ``timeout`` as a float if it is a number of seconds >= 0 (0: never retry)."""
    if not timeout >= 0:
        raise ValueError(f"expected reconnect_timeout >= 0 seconds, got {timeout}")
    return float(timeout)


@dataclass(frozen=True)
class Reconnect:
    """How long, and how often, to repeat a call that the wire failed.

    The pause doubles from ``initial_backoff`` up to ``max_backoff``, each drawn between half
    and all of it so that many trainers do not reconnect in lockstep.

    Args:
        address: The server(s), for the message of the final error.
        timeout: Seconds from the first failure after which ``ServerUnavailable`` is
            raised; 0 raises the first error at once.
        initial_backoff: The first pause, in seconds.
        max_backoff: The cap of the doubling pause, in seconds.
        closed: True once retrying is pointless (the client was closed).
    """

    address: str
    timeout: float = DEFAULT_RECONNECT_TIMEOUT
    initial_backoff: float = 0.05
    max_backoff: float = 1.0
    closed: Callable[[], bool] = lambda: False

    def run(
        self, attempt: Callable[[bool], _T], *, sleep: Callable[[float], None] = time.sleep
    ) -> _T:
        """Returns ``attempt(retrying)``, repeated while the wire fails, up to the deadline.

        Args:
            attempt: The call; its argument is True on a repetition, when the state of the
                sessions is unknown and the attempt may first look at it.
            sleep: How to pause (tests replace it).

        Raises:
            ServerUnavailable: Still failing after ``timeout`` seconds (the last error is
                its cause).
            EsaError: Any other error of ``attempt``, at once.
        """
        start, pause, retrying = time.monotonic(), self.initial_backoff, False
        while True:
            try:
                return attempt(retrying)
            except RetriableErrors as err:
                if self.timeout <= 0 or self.closed():
                    raise
                waited = time.monotonic() - start
                if waited >= self.timeout:
                    raise self.gave_up(waited, err) from err
                sleep(min(pause * random.uniform(0.5, 1.0), self.timeout - waited))
                pause = min(pause * 2, self.max_backoff)
                retrying = True

    def gave_up(self, waited: float, last: EsaError) -> ServerUnavailable:
        """The error raised once the deadline has passed."""
        return ServerUnavailable(
            f"esa server at {self.address} unreachable: gave up after {waited:.1f} s of "
            f"retrying (reconnect_timeout={self.timeout:g} s); last error: {last}",
            StatusCode.UNAVAILABLE,
        )

"""What ESASAC and ESAPPO share: constructor arguments, the lazy ESA runtime, logging, saving."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces

from ..config import EsaConfig
from .runtime import EsaRuntime


def tile_obs(obs: th.Tensor | dict[str, th.Tensor], reps: int) -> th.Tensor | dict[str, th.Tensor]:
    """Repeats a batch of observations ``reps`` times along the batch axis."""
    if isinstance(obs, dict):
        return {key: value.repeat(reps, *([1] * (value.dim() - 1))) for key, value in obs.items()}
    return obs.repeat(reps, *([1] * (obs.dim() - 1)))


class EsaMixin:
    """Adds an ESA runtime to an SB3 algorithm; put it first in the bases.

    The runtime (server connection and sessions) is created on the first rollout
    from the current env, dropped on ``set_env`` and never saved: a loaded model
    connects again (to ``esa_address``, or a newly spawned server) when it trains.
    """

    esa: EsaConfig
    esa_address: str | None
    _esa: EsaRuntime | None

    def __init__(
        self,
        policy: Any,
        env: Any,
        *args: Any,
        esa: EsaConfig | None = None,
        esa_address: str | None = None,
        **kwargs: Any,
    ) -> None:
        """Creates the SB3 model; the ESA sessions are created when training starts.

        Args:
            policy: As for the SB3 algorithm.
            env: As for the SB3 algorithm.
            *args: Further positional arguments of the SB3 algorithm.
            esa: The ESA hyperparameters (default ``EsaConfig()``).
            esa_address: An esa-server address; None spawns a private server.
            **kwargs: Any other argument of the SB3 algorithm.

        Raises:
            ValueError: If the action space is not a Box.
        """
        # Set before the SB3 constructor: it may set up the model, which can read them.
        self.esa = esa if esa is not None else EsaConfig()
        self.esa_address = esa_address
        self._esa = None
        super().__init__(policy, env, *args, **kwargs)  # type: ignore[call-arg]
        space = self.action_space  # type: ignore[attr-defined]
        if space is not None and not isinstance(space, spaces.Box):
            raise ValueError(f"expected a Box action space for ESA, got {space}")

    def _esa_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounds of the action space ESA probes in (overridden per algorithm)."""
        raise NotImplementedError

    def _esa_runtime(self) -> EsaRuntime:
        if self._esa is None:
            low, high = self._esa_bounds()
            self._esa = EsaRuntime(self.esa, self.esa_address, self.env, low, high)
        return self._esa

    def esa_close(self) -> None:
        """Closes the ESA sessions and stops a spawned server (also done on garbage collection)."""
        if self._esa is not None:
            self._esa.close()
            self._esa = None

    def set_env(self, env: Any, force_reset: bool = True) -> None:
        """Sets a new env; the ESA sessions are re-created for it on the next rollout."""
        self.esa_close()
        super().set_env(env, force_reset)  # type: ignore[misc]

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_esa"]  # type: ignore[misc]

    def dump_logs(self, *args: Any, **kwargs: Any) -> None:
        """Records the ESA statistics, then dumps the logs as SB3 does."""
        if self._esa is not None:
            self._esa.record(self.logger)  # type: ignore[attr-defined]
        super().dump_logs(*args, **kwargs)  # type: ignore[misc]

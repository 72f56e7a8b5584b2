"""What the drop-ins share: arguments, the lazy ESA runtime, the placebo, logging, saving."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
import torch as th
from gymnasium import spaces

from ..common.controls import Control, RandomDirections, check_control, shift_report
from ..common.runtime import (
    Engine,
    EsaRuntime,
    OnUnavailable,
    check_on_unavailable,
    choose_engine,
)
from ..config import EsaConfig, SessionConfig
from ..env_dt import env_dt
from ..reconnect import DEFAULT_RECONNECT_TIMEOUT, check_reconnect_timeout

if TYPE_CHECKING:
    # The mixin is always combined with an SB3 algorithm (ESAPPO, ESASAC): checked as one.
    from stable_baselines3.common.base_class import BaseAlgorithm as _Algorithm
else:
    _Algorithm = object


def tile_obs(obs: th.Tensor | dict[str, th.Tensor], reps: int) -> th.Tensor | dict[str, th.Tensor]:
    """Repeats a batch of observations ``reps`` times along the batch axis."""
    if isinstance(obs, dict):
        return {key: value.repeat(reps, *([1] * (value.dim() - 1))) for key, value in obs.items()}
    return obs.repeat(reps, *([1] * (obs.dim() - 1)))


class EsaMixin(_Algorithm):
    """Adds an ESA runtime to an SB3 algorithm; put it first in the bases.

    The runtime (server connection and sessions) is created on the first rollout
    from the current env, dropped on ``set_env`` and never saved: a loaded model
    connects again (to ``esa_address``, or a newly spawned server) when it trains.
    """

    esa: EsaConfig
    esa_address: str | None
    esa_engine: Engine | None
    esa_control: Control | None
    _esa: EsaRuntime | None
    _esa_placebo: RandomDirections | None

    def __init__(
        self,
        policy: Any,
        env: Any,
        *args: Any,
        esa: EsaConfig | Mapping[str, Any] | None = None,
        esa_address: str | None = None,
        esa_spawn: dict[str, Any] | None = None,
        esa_engine: Engine | None = None,
        esa_reconnect_timeout: float = DEFAULT_RECONNECT_TIMEOUT,
        esa_on_unavailable: OnUnavailable = "raise",
        esa_control: Control | None = None,
        **kwargs: Any,
    ) -> None:
        """Creates the SB3 model; the ESA sessions are created when training starts.

        Args:
            policy: As for the SB3 algorithm.
            env: As for the SB3 algorithm.
            *args: Further positional arguments of the SB3 algorithm.
            esa: The ESA hyperparameters: an ``EsaConfig``, or a dict of ``EsaConfig`` fields
                (an RL Zoo yaml file's ``esa: {amplitude: 0.2}``) applied over the family's
                default, checked like ``EsaConfig`` (``ValueError``); ``"preset": "paper"``
                starts from ``EsaConfig.paper()`` instead. None: the family's default.
            esa_address: An esa-server address (``host:port`` or ``unix:/path``), reached
                over plaintext gRPC (a TLS or Zenoh client goes through
                :meth:`EsaRuntime.on_client`); None: in-process, or a private server with
                ``esa_engine="sidecar"``.
            esa_spawn: Arguments of :meth:`EsaClient.spawn` for that private server, e.g.
                ``{"session_ttl": 3600}`` when rollouts are far apart, or
                ``{"transport": "zenoh"}``.
            esa_engine: Where the sessions live: ``"inprocess"`` (esa-core in this process:
                no server, nothing shared) or ``"sidecar"`` (an esa-server: ``esa_address``,
                else a private one). None: the server that ``esa_address`` or ``esa_spawn``
                describe, else ``"inprocess"`` (the SB3 guide's "Engines").
            esa_reconnect_timeout: Seconds a rollout waits for an unreachable server
                (restarting, stalled, connection lost), retrying with backoff, before
                ``esa_on_unavailable`` applies.
            esa_on_unavailable: ``"raise"`` (end training with ``ServerUnavailable``) or
                ``"skip"`` (no ESA until the next episode start; counted in the logger
                as ``esa/unavailable_steps``).
            esa_control: None (ESA), or a control that shares everything with ESA but what
                it tests, to judge ESA on your task (:mod:`esa_client.common.controls`):
                ``"placebo"`` (ESA's shift sizes, schedule and correlation in a random
                direction per env and episode, seeded from ``seed``) or ``"gradient"`` (a
                step of the trust region's size along the critic's action gradient; no
                session).
            **kwargs: Any other argument of the SB3 algorithm.

        Raises:
            ValueError: If the action space is not a Box, ``esa_control`` is unknown, or an
                ESA setting does not fit the env (checked here, before any training: a
                frequency past the Nyquist limit of the env's ``dt``, per-dimension vectors of
                the wrong length).
        """
        # Set before the SB3 constructor: it may set up the model, which can read them.
        self.esa = self._esa_config(esa)
        self.esa_address = esa_address
        self.esa_spawn = dict(esa_spawn or {})
        choose_engine(esa_engine, esa_address, self.esa_spawn)  # a bad choice fails here
        self.esa_engine = esa_engine
        self.esa_reconnect_timeout = check_reconnect_timeout(esa_reconnect_timeout)
        self.esa_on_unavailable = check_on_unavailable(esa_on_unavailable)
        self.esa_control = check_control(esa_control)
        self._esa = None
        self._esa_placebo = None
        super().__init__(policy, env, *args, **kwargs)
        # Model.load(path) without an env constructs the model with none: no action space yet.
        space = getattr(self, "action_space", None)
        if space is not None and not isinstance(space, spaces.Box):
            raise ValueError(f"expected a Box action space for ESA, got {space}")
        if self.env is not None:
            self._esa_session_config()

    @staticmethod
    def _default_esa() -> EsaConfig:
        """The family's shipped default, used when ``esa`` is not given."""
        return EsaConfig()

    @classmethod
    def _esa_config(cls, esa: EsaConfig | Mapping[str, Any] | None) -> EsaConfig:
        """``esa`` as an ``EsaConfig``: a dict's fields over the family's default (or a preset)."""
        if esa is None:
            return cls._default_esa()
        if isinstance(esa, EsaConfig):
            return esa
        if not isinstance(esa, Mapping):
            raise ValueError(f"expected esa to be an EsaConfig or a dict, got {esa!r}")
        values = dict(esa)
        preset = values.pop("preset", "default")
        if preset not in ("default", "paper"):
            raise ValueError(f"esa: preset must be 'default' or 'paper', got {preset!r}")
        names = {field.name for field in dataclasses.fields(EsaConfig)}
        unknown = sorted(str(key) for key in values if key not in names)
        if unknown:
            raise ValueError(
                f"esa: unknown EsaConfig field(s) {', '.join(unknown)}; "
                f"the fields are {', '.join(sorted(names))}"
            )
        base = EsaConfig.paper() if preset == "paper" else cls._default_esa()
        return dataclasses.replace(base, **values)  # __post_init__ checks every field

    def _esa_space(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Bounds of the action space ESA shifts in; None where it is unbounded."""
        raise NotImplementedError

    def _esa_box(self) -> spaces.Box:
        """The action space, a Box (the constructor checked it)."""
        space = self.action_space
        assert isinstance(space, spaces.Box)
        return space

    def _esa_env_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounds the env's actions are clipped to, in the space ESA works in."""
        space = self._esa_box()
        return space.low.reshape(-1), space.high.reshape(-1)

    def _esa_session_config(self) -> SessionConfig:
        low, high = self._esa_space()
        dim = self._esa_env_bounds()[0].size
        return self.esa.session_config(dim, env_dt(self.env, self.esa.dt), low, high)

    def _esa_runtime(self) -> EsaRuntime:
        if self._esa is None:
            assert self.env is not None, "ESA steps run in rollouts, which need an env"
            clip_low, clip_high = self._esa_env_bounds()
            self._esa = EsaRuntime(
                self.esa,
                self._esa_session_config(),
                self.env.num_envs,
                clip_low,
                clip_high,
                address=self.esa_address,
                spawn=self.esa_spawn,
                engine=self.esa_engine,
                # Models saved before these existed load without them.
                reconnect_timeout=getattr(self, "esa_reconnect_timeout", DEFAULT_RECONNECT_TIMEOUT),
                on_unavailable=getattr(self, "esa_on_unavailable", "raise"),
            )
        return self._esa

    def _esa_strength(self) -> float:
        """ESA's strength under the config's fade at this point of ``learn()``'s budget."""
        # SB3 sets _total_timesteps to where the current learn() ends, counted like
        # num_timesteps (a learn() that keeps the count fades over the whole count).
        total = max(getattr(self, "_total_timesteps", 0), 1)
        return self.esa.strength(self.num_timesteps / total)

    def _placebo(self, shift: np.ndarray, episode_starts: np.ndarray) -> np.ndarray:
        """ESA's ``shift`` ``(N, D)`` in the placebo's random directions.

        The directions live with the sessions: drawn anew for a new env, seeded from the
        model's ``seed``.
        """
        if self._esa_placebo is None:
            n_envs, action_dim = shift.shape
            self._esa_placebo = RandomDirections(n_envs, action_dim, self.seed)
        return self._esa_placebo(shift, episode_starts)

    def _report_shift(
        self,
        sampled: np.ndarray,
        shift: np.ndarray,
        mean: np.ndarray,
        std: np.ndarray,
        low: np.ndarray,
        high: np.ndarray,
        kappa: float | None,
        strength: float,
    ) -> None:
        """Averages :func:`shift_report` of one step, and ESA's strength, into the logger.

        ``std`` is the unfaded action scale and ``kappa`` the trust region (None: no bound).
        """
        bound = None if kappa is None else strength * kappa
        for key, value in shift_report(sampled, shift, mean, std, low, high, bound).items():
            self.logger.record_mean(f"esa/{key}", value)
        self.logger.record_mean("esa/strength", strength)

    def esa_close(self) -> None:
        """Closes the ESA sessions and stops a spawned server (also done on garbage collection)."""
        if self._esa is not None:
            self._esa.close()
            self._esa = None
        self._esa_placebo = None

    def set_env(self, env: Any, force_reset: bool = True) -> None:
        """Sets a new env; the ESA sessions are re-created for it on the next rollout."""
        self.esa_close()
        super().set_env(env, force_reset)

    def _excluded_save_params(self) -> list[str]:
        # Where the sessions live belongs to the machine that trains, not to the model (a
        # spawn's arguments may hold a token): a loaded model takes them as load kwargs,
        # ``Model.load(path, env, esa_address=...)``, else runs in-process.
        # The placebo's signs belong to one run on one VecEnv, like the sessions.
        excluded = ["_esa", "_esa_placebo", "esa_address", "esa_spawn"]
        return [*super()._excluded_save_params(), *excluded]

    def dump_logs(self, *args: Any, **kwargs: Any) -> None:
        """Records the ESA statistics, then dumps the logs as SB3 does."""
        if self._esa is not None:
            self._esa.record(self.logger)
        super().dump_logs(*args, **kwargs)

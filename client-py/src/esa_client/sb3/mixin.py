"""What the drop-ins share: arguments, the lazy ESA runtime and control, logging, saving."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import torch as th
from gymnasium import spaces

from ..client import EsaClient, Where, resolve_client
from ..common.action_frame import ActionFrame
from ..common.controls import (
    Arrays,
    Control,
    EsaShift,
    check_control,
    control_shift,
    shift_report,
)
from ..common.runtime import EsaRuntime, OnUnavailable, check_on_unavailable
from ..config import EsaConfig, SessionConfig
from ..env_dt import env_dt

if TYPE_CHECKING:  # the mixin is always combined with an SB3 algorithm: checked as one
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

    The client is opened (and its server checked) when the model is built or loaded; the
    sessions are created on the first rollout with ESA, closed on ``set_env``; neither is
    saved (the SB3 guide's "Engines").
    """

    esa: EsaConfig
    esa_client: EsaClient
    esa_control: Control | None
    _esa: EsaRuntime | None
    _esa_control_shift: EsaShift | None
    _esa_owns_client = False
    _esa_frame: ActionFrame | None = None

    def __init__(
        self,
        policy: Any,
        env: Any,
        *args: Any,
        esa: EsaConfig | Mapping[str, Any] | None = None,
        esa_client: Where = None,
        esa_on_unavailable: OnUnavailable = "raise",
        esa_control: Control | None = None,
        **kwargs: Any,
    ) -> None:
        """Creates the SB3 model and opens the ESA client; sessions come with training.

        Args:
            policy: As for the SB3 algorithm.
            env: As for the SB3 algorithm.
            *args: Further positional arguments of the SB3 algorithm.
            esa: An ``EsaConfig``, or a dict of its fields (RL Zoo's ``esa: {amplitude: 0.2}``)
                over the family's default (``"preset": "paper"``: over ``EsaConfig.paper()``).
                None: the family's default.
            esa_client: Where the sessions live. None: esa-core in this process. An
                :class:`~esa_client.EsaClient`, which stays yours to close. Or a string that
                :meth:`EsaClient.open <esa_client.EsaClient.open>` parses (``"host:port"``,
                ``"unix:/path"``, ``"zenoh:<endpoint>"``, ``"spawn"``; the SB3 guide's
                "Engines").
            esa_on_unavailable: Once the server stayed unreachable for the client's
                ``reconnect_timeout``: ``"raise"`` (``ServerUnavailable``) or ``"skip"`` (no
                ESA until the next episode start; ``esa/unavailable_steps``).
            esa_control: None (ESA), or a control to judge ESA on your task
                (:mod:`esa_client.common.controls`): ``"placebo"`` (ESA's shift sizes in a
                random direction per env and episode, seeded from ``seed``) or
                ``"gradient"`` (the trust region's step along the critic's action gradient).
            **kwargs: Any other argument of the SB3 algorithm.

        Raises:
            ValueError: If the action space is not a Box, ``esa_client`` or ``esa_control`` is
                unknown, or an ESA setting does not fit the env (Nyquist for its ``dt``,
                per-dimension lengths).
            ServerUnavailable: If no server answers at ``esa_client``'s address.
            Unauthenticated: If the server there refuses the client.
        """
        # Set before the SB3 constructor: it may set up the model, which can read them.
        self.esa = self._esa_config(esa)
        self.esa_on_unavailable = check_on_unavailable(esa_on_unavailable)
        self.esa_control = check_control(esa_control)
        self._esa = None
        self._esa_control_shift = None
        self._esa_open(esa_client)
        try:
            super().__init__(policy, env, *args, **kwargs)
            # Model.load(path) without an env builds a model with no action space.
            space = getattr(self, "action_space", None)
            if space is not None and not isinstance(space, spaces.Box):
                raise ValueError(f"expected a Box action space for ESA, got {space}")
            if self.env is not None:
                self._esa_session_config()
        except BaseException:
            self.esa_close()
            raise

    def _esa_open(self, where: Where) -> None:
        """Opens (and checks) the client ``where`` names; closes one this model opened before."""
        client, owned = resolve_client(where)
        if self._esa_owns_client and getattr(self, "esa_client", None) is not client:
            self.esa_client.close()
        self.esa_client, self._esa_owns_client = client, owned

    @classmethod
    def load(cls, path: Any, env: Any = None, *args: Any, **kwargs: Any) -> Any:
        """Loads a model as SB3 does; ``esa_client=`` says where its sessions live.

        Raises:
            ServerUnavailable: If no server answers at ``esa_client``'s address.
        """
        where = kwargs.pop("esa_client", None)
        model = super().load(path, env, *args, **kwargs)
        model._esa_open(where)
        return model

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

    def _make_esa_frame(self, box: spaces.Box) -> ActionFrame:
        """The units the family shifts ``box``'s actions in."""
        raise NotImplementedError

    @property
    def esa_frame(self) -> ActionFrame:
        """The action space as ESA sees it, built once per model from its Box."""
        if self._esa_frame is None:
            space = self.action_space
            assert isinstance(space, spaces.Box)  # checked by the constructor
            self._esa_frame = self._make_esa_frame(space)
        return self._esa_frame

    def _esa_session_config(self) -> SessionConfig:
        frame = self.esa_frame
        dt = env_dt(self.env, self.esa.dt)
        return self.esa.session_config(frame.dim, dt, *frame.session_bounds())

    def _esa_runtime(self) -> EsaRuntime:
        if self._esa is None:
            assert self.env is not None, "ESA steps run in rollouts, which need an env"
            self._esa = EsaRuntime(
                self.esa,
                self.esa_client,
                self._esa_session_config(),
                self.env.num_envs,
                self.esa_frame.low,
                self.esa_frame.high,
                on_unavailable=self.esa_on_unavailable,
            )
        return self._esa

    def _esa_strength(self) -> float:
        """ESA's strength under the config's fade at this point of ``learn()``'s budget.

        SB3's ``_total_timesteps`` is where this ``learn()`` ends, counted like ``num_timesteps``.
        """
        total = max(getattr(self, "_total_timesteps", 0), 1)
        return self.esa.strength(self.num_timesteps / total)

    def _control_shift(self) -> EsaShift:
        """ESA's shift or its control's, built and dropped with the sessions (new placebo signs)."""
        if self._esa_control_shift is None:
            self._esa_control_shift = control_shift(self.esa_control, self.seed)
        return self._esa_control_shift

    def _report_shift(self, strength: float, arrays: Arrays) -> None:
        """Averages :func:`shift_report` of one step (``std`` unfaded), and ESA's strength."""
        kappa = self._control_shift().bound(self.esa.trust_region)
        bound = None if kappa is None else strength * kappa
        for key, value in shift_report(*arrays, bound=bound).items():
            self.logger.record_mean(f"esa/{key}", value)
        self.logger.record_mean("esa/strength", strength)

    def _esa_close_sessions(self) -> None:
        if self._esa is not None:
            self._esa.close()
            self._esa = None
        self._esa_control_shift = None

    def esa_close(self) -> None:
        """Closes the ESA sessions, and the client if the model opened it (a spawned server too)."""
        self._esa_close_sessions()
        if self._esa_owns_client:
            self.esa_client.close()

    def set_env(self, env: Any, force_reset: bool = True) -> None:
        """Sets a new env; the ESA sessions are re-created for it on the next rollout."""
        self._esa_close_sessions()
        super().set_env(env, force_reset)

    def _excluded_save_params(self) -> list[str]:
        # The client belongs to the machine that trains (it may hold a token); the control
        # (the placebo's signs) to one run on one VecEnv, like the sessions.
        excluded = ["_esa", "_esa_control_shift", "esa_client", "_esa_owns_client", "_esa_frame"]
        return [*super()._excluded_save_params(), *excluded]

    def dump_logs(self, *args: Any, **kwargs: Any) -> None:
        """Records the ESA statistics, then dumps the logs as SB3 does."""
        if self._esa is not None:
            self._esa.record(self.logger)
        super().dump_logs(*args, **kwargs)

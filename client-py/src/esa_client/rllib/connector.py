"""``EsaModuleToEnv``: the module-to-env ConnectorV2 piece that applies ESA on an EnvRunner.

Placed before ``NormalizeAndClipActions``, the action it writes is what the env executes and
the episode stores: for SAC clipped to [-1, 1], for PPO unclipped, with ``action_logp`` left
at ``log pi_old(a_t)``, the shifted action's exact behaviour log-probability (``v(t)`` does not
depend on ``a_t``).

The autoreset step, whose action RLlib discards, starts the new session episode (its probe
moves nothing), so the session's episode count stays the env's.
"""

from __future__ import annotations

import contextlib
import functools
import weakref
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

# Loaded before any gRPC channel exists (as in esa_client.sb3): a local EnvRunner's learner
# steps its optimizer while the connector's StepStream is open.
import torch._dynamo  # noqa: F401  (imported for its side effect)
from ray.rllib.connectors.connector_v2 import ConnectorV2
from ray.rllib.core.columns import Columns

from ..client import EsaClient
from ..common.controls import Control, check_control, control_shift, gradient_size, unit_gradient
from ..common.head_step import head_critic, head_shift, shifted
from ..common.runtime import EsaRuntime
from ..config import EsaConfig
from ..env_dt import env_dt
from ..errors import ServerUnavailable
from .modules import ESA_OBS, EsaModuleMixin, EsaPPOTorchRLModule
from .service import EsaService

ESA_SHIFT = "esa_shift"
"""Optional extra model output (``record_shift=True``): ``a_t + v(t) - a_t`` per step."""


class _Metrics:
    """EsaRuntime.record's logger interface over RLlib's MetricsLogger (None: no logging)."""

    def __init__(self, metrics: Any, window: int) -> None:
        self.metrics, self.window = metrics, window

    def record(self, key: str, value: Any) -> None:
        if self.metrics is None:
            return
        if key.endswith(("sessions_restored", "reconnects")):
            self.metrics.log_value(key, value, reduce="sum")
        else:
            self.metrics.log_value(key, value, reduce="mean", window=self.window)


def vector_env_dt(env: Any) -> float | None:
    """Seconds per step of a gymnasium vector env's copies (None without env or dt)."""
    with contextlib.suppress(ValueError):
        return None if env is None else env_dt(env)
    return None


def _obs_tensor(items: list[Any], device: torch.device) -> Any:
    if isinstance(items[0], dict):
        return {k: _obs_tensor([item[k] for item in items], device) for k in items[0]}
    return torch.as_tensor(np.stack([np.asarray(item) for item in items]), device=device)


def _tile(value: Any, reps: int) -> Any:
    if isinstance(value, dict):
        return {k: _tile(v, reps) for k, v in value.items()}
    return value.repeat(reps, *([1] * (value.dim() - 1)))


class _Rows:
    """The per-env-copy items of the unbatched columns, row r being env copy r.

    A copy autoreset on this step appears under its finished episode's id.
    """

    def __init__(
        self, batch: dict[str, Any], episodes: list[Any], shared_data: dict[str, Any] | None
    ) -> None:
        self.batch = batch
        column = batch[Columns.ACTIONS]
        structure = (shared_data or {}).get("memorized_map_structure")
        keys = [(eps_id,) for eps_id in structure] if isinstance(structure, list) else list(column)
        if not (
            isinstance(column, dict)
            and len(keys) == len(episodes) == len(column)
            and set(keys) == set(column)
            and all(k == (ep.id_,) for k, ep in zip(keys, episodes, strict=False) if ep.is_reset)
        ):
            raise ValueError(
                "expected one action per env copy, keyed by episode id in env order (a "
                f"single-agent EnvRunner), got keys {list(column)[:8]} for "
                f"episodes {[episode.id_ for episode in episodes][:8]}"
            )
        self.keys = keys

    def get(self, name: str) -> list[Any]:
        return [self.batch[name][key][0] for key in self.keys]

    def put(self, name: str, values: list[Any]) -> None:
        self.batch[name] = {key: [value] for key, value in zip(self.keys, values, strict=True)}


def _close(runtime: EsaRuntime, client: EsaClient) -> None:
    runtime.close()
    client.close()


class EsaModuleToEnv(ConnectorV2):
    """Module-to-env piece: Algorithm 1's action ``a_t + v(t)`` for every env copy.

    It acts only when exploring and while the module's ``esa_active`` (the learner's gate)
    is set; otherwise the actions pass through, and the sessions start new episodes when ESA
    acts again. The sessions (one per env copy) are created on the first step that needs
    them, so an EnvRunner without env never connects. PPO modules step as ``ESAPPO`` does,
    SAC modules as ``ESASAC``, at the strength the learner's fade set. Logged under
    ``env_runners/esa/``: ``active``, ``strength``, the runtime's statistics, ``reconnects``.

    Args:
        service: Where the sessions live (default: in this runner's process).
        dt: Seconds per env step when ``EsaConfig.dt`` is None.
        control: None (ESA), ``"placebo"`` or ``"gradient"``: the drop-ins' ``esa_control``.
        record_shift: Also output column ``esa_shift``, the shift applied, for diagnostics.
        metrics_window: Window of the mean ESA statistics.

    Raises:
        ValueError: If ``esa`` is not an EsaConfig or ``control`` is unknown.
    """

    def __init__(
        self,
        input_observation_space: Any = None,
        input_action_space: Any = None,
        *,
        esa: EsaConfig,
        service: EsaService | None = None,
        dt: float | None = None,
        control: Control | None = None,
        record_shift: bool = False,
        metrics_window: int = 1000,
        **kwargs: Any,
    ) -> None:
        """Builds the piece; nothing connects before the first exploring step."""
        super().__init__(input_observation_space, input_action_space, **kwargs)
        if not isinstance(esa, EsaConfig):
            raise ValueError(f"expected esa to be an EsaConfig, got {esa!r}")
        self.esa = esa
        self.control = check_control(control)
        # The placebo's directions are this runner's (copies and reopened sessions keep them):
        # their seed comes from numpy's global generator, which the EnvRunner seeded with
        # config.seed plus its worker index before building this piece, so with
        # debugging(seed=...) they repeat run to run and differ between runners.
        self._seed = int(np.random.randint(2**31 - 1)) if self.control == "placebo" else None
        self._rule = control_shift(self.control, self._seed)
        self.service = service if service is not None else EsaService()
        self.dt, self.record_shift, self.metrics_window = dt, record_shift, metrics_window
        self._runtime: EsaRuntime | None = None
        self._finalizer: weakref.finalize[Any, Any] | None = None
        # Whether the last step went through ESA: if not, the sessions missed episode ends.
        self._active = False
        # Env copies whose last step was an autoreset step (it started their episode).
        self._autoreset = np.zeros(0, dtype=bool)
        self.reconnects = 0

    def __getstate__(self) -> dict[str, Any]:
        """Pickles (and deep-copies) the settings only: a copy opens its own sessions."""
        rule = control_shift(self.control, self._seed)
        return dict(self.__dict__, _runtime=None, _finalizer=None, _active=False, _rule=rule)

    @property
    def runtime(self) -> EsaRuntime | None:
        """The sessions of this EnvRunner's env copies (None before the first ESA step)."""
        return self._runtime

    def close(self) -> None:
        """Closes the sessions and the client; a later step reopens them."""
        if self._finalizer is not None:
            self._finalizer()
        self._runtime = self._finalizer = None
        self._rule = control_shift(self.control, self._seed)
        self._active = False

    def _open(self, module: EsaModuleMixin, n_envs: int) -> EsaRuntime:
        dt = self.esa.dt if self.esa.dt is not None else self.dt
        if dt is None:
            raise ValueError(
                "expected the env to define dt or metadata['render_fps'], got neither; "
                "set EsaConfig(dt=...) to the seconds per environment step"
            )
        frame, unavailable = module.esa_frame, self.service.on_unavailable
        config = self.esa.session_config(frame.dim, dt, *frame.session_bounds())
        client = self.service.connect()
        try:
            runtime = EsaRuntime(
                self.esa, client, config, n_envs, frame.low, frame.high, on_unavailable=unavailable
            )
        except BaseException:
            client.close()
            raise
        self._finalizer = weakref.finalize(self, _close, runtime, client)
        self._runtime = runtime
        self._autoreset = np.zeros(n_envs, dtype=bool)
        return runtime

    def __call__(
        self,
        *,
        rl_module: Any,
        batch: dict[str, Any],
        episodes: list[Any],
        explore: bool | None = None,
        shared_data: dict[str, Any] | None = None,
        metrics: Any = None,
        **kwargs: Any,
    ) -> Any:
        """Replaces the sampled actions by ``a_t + v(t)`` (exploring, gate open)."""
        if ESA_OBS not in batch:
            return batch
        obs_column = batch.pop(ESA_OBS)
        if not explore:
            self._active = False
            return batch
        if not isinstance(rl_module, EsaModuleMixin):
            raise ValueError(
                "expected an ESA RLModule (EsaSACTorchRLModule or EsaPPOTorchRLModule, "
                f"set by with_esa) on the EnvRunner, got {type(rl_module).__name__}"
            )
        log = _Metrics(metrics, self.metrics_window)
        active = rl_module.esa_is_active()
        log.record("esa/active", float(active))
        rows = _Rows(batch, episodes, shared_data)
        n = len(episodes)
        sampled_rows = [np.asarray(a) for a in rows.get(Columns.ACTIONS)]
        like = sampled_rows[0]
        sample = np.stack(sampled_rows).reshape(n, -1)
        if not active:
            self._active = False
            self._record_shift(rows, np.zeros(sample.shape), like)
            return batch
        runtime = self._runtime if self._runtime is not None else self._open(rl_module, n)
        if not self._active:
            runtime.batch.reset()
            self._autoreset[:] = False
        self._active = True
        # Not reset yet: RLlib autoresets this copy on this step and discards its action.
        autoreset = np.array([not episode.is_reset for episode in episodes])
        fresh = np.array([episode.is_reset and episode.t == 0 for episode in episodes])
        starts = autoreset | (fresh & ~self._autoreset)
        self._autoreset = autoreset
        device = next(iter(rl_module.parameters())).device
        strength = float(rl_module.esa_strength.item())
        log.record("esa/strength", strength)
        with torch.no_grad():
            obs = _obs_tensor([obs_column[key][0] for key in rows.keys], device)
            dist_rows = np.stack(rows.get(Columns.ACTION_DIST_INPUTS))
            dist_inputs = torch.as_tensor(dist_rows, device=device)
        try:
            executed = self._step(rl_module, runtime, obs, dist_inputs, sample, starts, strength)
        except ServerUnavailable:
            # The server stayed away (on_unavailable="raise"): reconnect once more, e.g. to
            # a server restarted since; every session starts an episode.
            self.close()
            self.reconnects += 1
            log.record("esa/reconnects", 1)
            runtime = self._open(rl_module, n)
            every = np.ones(n, dtype=bool)
            executed = self._step(rl_module, runtime, obs, dist_inputs, sample, every, strength)
            self._active = True
        if metrics is not None:
            runtime.record(log)
        rows.put(Columns.ACTIONS, [row.astype(like.dtype).reshape(like.shape) for row in executed])
        self._record_shift(rows, executed.astype(np.float64) - sample, like)
        return batch

    def _step(
        self,
        module: EsaModuleMixin,
        runtime: EsaRuntime,
        obs: Any,
        dist_inputs: torch.Tensor,
        sample: np.ndarray,
        starts: np.ndarray,
        strength: float,
    ) -> np.ndarray:
        """The env copies' actions under ESA (or its control), as the drop-in computes them."""
        size = gradient_size(strength, self.esa.trust_region)
        if isinstance(module, EsaPPOTorchRLModule):
            frame = module.esa_frame
            mean_t, log_std_t = dist_inputs.chunk(2, dim=-1)
            mean, std = mean_t.cpu().numpy(), log_std_t.exp().cpu().numpy()
            critic = head_critic(module.esa_head, module.esa_features(obs), frame, mean, std)

            execute = functools.partial(shifted, sample)

            def head_session() -> tuple[np.ndarray, np.ndarray]:
                closed = critic.closed_form()
                shift = head_shift(runtime, closed, critic.std, frame, sample, starts, strength)
                return execute(shift), shift

            def head_gradient() -> np.ndarray:
                scaled = (sample - frame.center) / frame.half_width
                shift: np.ndarray = size * unit_gradient(critic.gradient(scaled)) * std
                return shift

            return self._rule.act(head_session, head_gradient, execute, starts)[0]
        n = len(sample)
        sampled = sample.astype(np.float64)
        with torch.no_grad():
            scale = module.esa_scale(dist_inputs).double().cpu().numpy()

        def q_fn(points: np.ndarray) -> np.ndarray:
            reps = len(points) // n
            with torch.no_grad():
                actions = torch.as_tensor(points, dtype=torch.float32, device=dist_inputs.device)
                q = module.esa_q(_tile(obs, reps), dist_inputs.repeat(reps, 1), actions)
                values: np.ndarray = q.double().cpu().numpy()
                return values

        def critic_session() -> tuple[np.ndarray, np.ndarray]:
            applied = runtime.step(sampled, starts, q_fn, scale, strength=strength)
            return applied, applied - sampled

        def critic_gradient() -> np.ndarray:
            actions = torch.as_tensor(sampled, dtype=torch.float32).requires_grad_(True)
            with torch.enable_grad():
                q = module.esa_q(obs, dist_inputs, actions).sum()
                (grad,) = torch.autograd.grad(q, actions)
            unit = unit_gradient(grad.cpu().numpy().astype(np.float64) * scale)
            shift: np.ndarray = size * scale * unit
            return shift

        def clipped(shift: np.ndarray) -> np.ndarray:
            actions: np.ndarray = np.clip(sampled + shift, -1.0, 1.0)
            return actions

        return self._rule.act(critic_session, critic_gradient, clipped, starts)[0]

    def _record_shift(self, rows: _Rows, shift: np.ndarray, like: np.ndarray) -> None:
        if self.record_shift:
            rows.put(ESA_SHIFT, [row.astype(np.float32).reshape(like.shape) for row in shift])


class ConnectorFactory:
    """``config.env_runners(module_to_env_connector=...)``: ``previous``, then EsaModuleToEnv."""

    def __init__(self, previous: Callable[..., Any] | None, **kwargs: Any) -> None:
        """Keeps the previous factory and the connector's arguments."""
        self.previous, self.kwargs = previous, kwargs

    def __call__(self, env: Any = None, spaces: Any = None) -> list[ConnectorV2]:
        """The pieces for one EnvRunner (``env`` is its vector env, or None)."""
        pieces = self.previous(env, spaces) if self.previous is not None else []
        if not isinstance(pieces, (list, tuple)):
            pieces = [pieces]
        return [*pieces, EsaModuleToEnv(dt=vector_env_dt(env), **self.kwargs)]

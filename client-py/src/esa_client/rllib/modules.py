"""RLModules whose env-runner copies keep the critic ESA probes.

RLlib builds every EnvRunner's module ``inference_only``, without SAC's Q networks (and PPO
has no action-value network), but ESA probes a critic on the env runners: these modules
keep SAC's and add ``ESAPPO``'s quadratic head, shipped with every weight sync, as are the
buffers ``esa_active`` (the learner's gate) and ``esa_strength`` (its fade). Extra networks
are initialized on a forked torch generator, so that the random streams stay RLlib's.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np
import torch
from ray.rllib.algorithms.ppo.torch.default_ppo_torch_rl_module import DefaultPPOTorchRLModule
from ray.rllib.algorithms.sac.torch.default_sac_torch_rl_module import DefaultSACTorchRLModule
from ray.rllib.core.columns import Columns
from ray.rllib.core.distribution.torch.torch_distribution import (
    TorchDiagGaussian,
    TorchSquashedGaussian,
)
from ray.rllib.core.learner.utils import make_target_network
from ray.rllib.core.models.base import ENCODER_OUT
from ray.rllib.utils.numpy import MAX_LOG_NN_OUTPUT, MIN_LOG_NN_OUTPUT

from ..common.action_frame import ActionFrame
from ..common.quadratic_head import QuadraticHead

ESA_OBS = "esa_obs"
"""Exploration output column: the observations the module acted on (removed by the connector)."""


def settings_of(module: Any) -> dict[str, Any]:
    """The ESA settings ``with_esa`` put into the module's ``model_config["esa"]``."""
    settings = (module.model_config or {}).get("esa")
    if not isinstance(settings, dict):
        raise ValueError(
            f"expected model_config['esa'] (set by esa_client.rllib.with_esa) in "
            f"{type(module).__name__}, got {settings!r}"
        )
    return dict(settings)


def _box(space: gym.Space[Any]) -> gym.spaces.Box:
    if not isinstance(space, gym.spaces.Box):
        raise ValueError(f"expected a Box action space for ESA, got {space}")
    return space


class EsaModuleMixin:
    """What :class:`~esa_client.rllib.connector.EsaModuleToEnv` asks of a module.

    Actions are in the module's own units: with ``normalize_actions=True``, the Box scaled
    to [-1, 1], as in ESAPPO and ESASAC.
    """

    esa_active: torch.Tensor
    esa_strength: torch.Tensor
    action_space: Any
    model_config: Any

    if TYPE_CHECKING:  # always combined with an RLlib TorchRLModule, an nn.Module

        def register_buffer(self, name: str, tensor: torch.Tensor | None) -> None:
            """``nn.Module.register_buffer``."""

        def parameters(self, recurse: bool = True) -> Iterator[torch.nn.Parameter]:
            """``nn.Module.parameters``."""

    def _setup_esa(self, distribution: type[Any], name: str) -> None:
        self.esa_settings = settings_of(self)
        self.esa_action_dim = int(np.prod(_box(self.action_space).shape))
        # Off until the learner says otherwise (with gate=None: at its first update).
        self.register_buffer("esa_active", torch.zeros((), dtype=torch.float32))
        self.register_buffer("esa_strength", torch.ones((), dtype=torch.float64))
        got: Any = self.get_exploration_action_dist_cls()  # type: ignore[attr-defined]
        if got is not distribution:
            raise ValueError(f"expected {name} for ESA, got {got.__name__}")

    def esa_is_active(self) -> bool:
        """Whether the learner's gate lets ESA shift actions now."""
        return bool(self.esa_active.item() > 0.5)

    @property
    def esa_frame(self) -> ActionFrame:
        """The action space as ESA sees it (the drop-ins' frame for the same family)."""
        raise NotImplementedError

    def esa_scale(self, dist_inputs: torch.Tensor) -> torch.Tensor:
        """The policy's standard deviation in action units, shape ``(N, D)``."""
        raise NotImplementedError

    def esa_q(self, obs: Any, dist_inputs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """The probed critic at ``(obs, actions)`` (rows aligned), shape ``(B,)``."""
        raise NotImplementedError

    def _forward_exploration(self, batch: dict[str, Any], **kwargs: Any) -> dict[str, Any]:
        # The RLModule's method, next in the MRO of the concrete classes below.
        out: dict[str, Any] = super()._forward_exploration(batch, **kwargs)  # type: ignore[misc]
        out[ESA_OBS] = batch[Columns.OBS]
        return out


class EsaSACTorchRLModule(EsaModuleMixin, DefaultSACTorchRLModule):
    """RLlib's default SAC module, keeping the probed target Q networks in its env-runner copy."""

    def setup(self) -> None:
        """Builds RLlib's SAC module, plus the probed Q networks when inference-only."""
        super().setup()
        self._setup_esa(TorchSquashedGaussian, "SAC's squashed Gaussian")
        if self.inference_only:
            # RLlib's setup skipped them; the learner's weights overwrite them at the first sync.
            catalog, framework = self.catalog, self.framework
            assert catalog is not None  # RLlib's default SAC module always has one
            names = ["qf", "qf_twin"] if self.twin_q else ["qf"]
            with torch.random.fork_rng(devices=[]):
                for name in names:
                    setattr(self, f"{name}_encoder", catalog.build_qf_encoder(framework=framework))
                    setattr(self, name, catalog.build_qf_head(framework=framework))
                for part in [part for name in names for part in (f"{name}_encoder", name)]:
                    setattr(self, f"target_{part}", make_target_network(getattr(self, part)))

    def get_non_inference_attributes(self) -> list[str]:
        """RLlib's list less the probed target networks: those are kept and shipped."""
        return ["qf", "qf_encoder"] + (["qf_twin", "qf_twin_encoder"] if self.twin_q else [])

    @property
    def esa_frame(self) -> ActionFrame:
        """SAC's squashed [-1, 1], where the sessions clip: ESASAC's frame."""
        return ActionFrame.squashed(_box(self.action_space))

    def esa_scale(self, dist_inputs: torch.Tensor) -> torch.Tensor:
        """``min((1 - tanh(mu)^2) std, 1)``: tanh's linearization at the mean, as ESASAC."""
        mean, log_std = dist_inputs.chunk(2, dim=-1)
        std = log_std.clamp(MIN_LOG_NN_OUTPUT, MAX_LOG_NN_OUTPUT).exp()
        return ((1.0 - torch.tanh(mean) ** 2) * std).clamp(max=1.0)

    def esa_q(self, obs: Any, dist_inputs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """The mean of the target twins (or the one target) at ``(obs, actions)``, ``(B,)``."""
        batch = {Columns.OBS: obs, Columns.ACTIONS: actions}
        names = ["qf", "qf_twin"] if self.twin_q else ["qf"]
        # RLlib's public Q methods (compute_q_values, forward_target) give the twins'
        # minimum only; its helper gives each. It returns a tensor (typed as a dict).
        nets = [(getattr(self, f"target_{n}_encoder"), getattr(self, f"target_{n}")) for n in names]
        q = [self._qf_forward_train_helper(batch, encoder, head) for encoder, head in nets]
        return torch.stack(cast(list[torch.Tensor], q), dim=1).mean(dim=1)

    def esa_mean_action(self, obs: Any) -> torch.Tensor:
        """The squashed policy's mean action ``tanh(mu(s))``."""
        logits = self.pi(self.pi_encoder({Columns.OBS: obs})[ENCODER_OUT])
        return torch.tanh(logits.chunk(2, dim=-1)[0])


class EsaPPOTorchRLModule(EsaModuleMixin, DefaultPPOTorchRLModule):
    """RLlib's default PPO module plus ``ESAPPO``'s quadratic head of ``z = (a - mu) / sigma``.

    :class:`~esa_client.rllib.learners.EsaPPOTorchLearner` fits the head, outside PPO's optimizer.
    """

    head_hidden = 64
    """Hidden units of each of the head's two layers (``ESAPPO.head_hidden``)."""

    def setup(self) -> None:
        """Builds RLlib's PPO module and the quadratic head."""
        super().setup()
        self._setup_esa(TorchDiagGaussian, "PPO's diagonal Gaussian")
        if self.model_config.get("use_lstm") or self.model_config.get("use_attention"):
            raise ValueError("expected a stateless PPO module for ESA, got a recurrent one")
        if self.observation_space is None:
            raise ValueError("expected an observation space for ESA's quadratic head, got None")
        features = int(gym.spaces.flatdim(self.observation_space))
        with torch.random.fork_rng(devices=[]):
            self.esa_head = QuadraticHead(features, self.esa_action_dim, self.head_hidden)

    @staticmethod
    def esa_features(obs: torch.Tensor) -> torch.Tensor:
        """The observation as the head sees it: flattened, float."""
        return obs.reshape(len(obs), -1).float()

    @property
    def esa_frame(self) -> ActionFrame:
        """ESAPPO's frame: the Box scaled to [-1, 1], where the sessions are unbounded."""
        box = _box(self.action_space)
        if self.esa_settings.get("normalize_actions", True):
            return ActionFrame.unit(box, bounded=False)
        return ActionFrame.scaled(box)

    def esa_scale(self, dist_inputs: torch.Tensor) -> torch.Tensor:
        """The Gaussian's standard deviation."""
        return dist_inputs.chunk(2, dim=-1)[1].exp()

    def esa_z(self, dist_inputs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Policy-normalized actions ``(a - mu) / sigma``."""
        mean, log_std = dist_inputs.chunk(2, dim=-1)
        return (actions.reshape(len(actions), -1) - mean) / log_std.exp()

"""Method name -> model constructor, with hyperparameters from ``configs/algorithms.toml``.

A method is an algorithm family (``ppo``, ``sac``, ``td3``, ``ddpg``) plus an
exploration add-on: none, ESA (``esa_client.sb3``), adaptive parameter noise
(:mod:`esa_experiments.param_noise`), Ornstein-Uhlenbeck action noise (DDPG) or pink
action noise (TD3; Eberhard et al., ICLR 2023). TD3 always explores with action noise,
Gaussian unless the method says pink; its ESA arms add ESA on top of that noise.

ESA methods use one preset, the same on every env (no per-env tuning): ``default`` is
``EsaConfig()`` (the confirmation campaign's PPO default), ``off_policy`` the off-policy
family's ``EsaConfig.off_policy()``, ``null`` ``EsaConfig()`` with learning rate 0 (the
shift stays 0: E1's critic fits), ``sine`` the off-policy default with learning rate 0
(with ``esa_execute='probe'``: exploration by the sinusoid alone), ``target`` the PPO
target mode's setting (the pick of the archived study ``target_search``, on
InvertedPendulum-v5 tuning seeds: ``results/target_search``), ``seeking_off_policy`` the
off-policy default faded over ``SEEKING_FADE`` of the budget (study ``seeking``). A
method's ``options`` are further drop-in arguments: the gradient controls
(``esa_shift='gradient'``: the same bound, normalisation and gate, the shift along the
critic's action gradient), the placebos (``esa_shift='placebo'``: ESA's shift sizes in
random directions), the mean anchor (``esa_anchor='mean'``) and the target mode. Each
run's sidecar stores its options (:data:`OPTION_DEFAULTS`); together they name a subclass
of :mod:`esa_experiments.lab` (:func:`esa_class`). The matched-noise arms are
plain TD3 whose noise has the variance of ``td3_sine``'s
executed probe (``noise_match``).

The RL Zoo3 arms (``ppo_zoo``, ``sac_zoo``, ``td3_zoo``; study ``zoo_baselines``) are plain
PPO, SAC and TD3 with RL Zoo3 2.9.2's tuned settings (``config``: their own tables of
``algorithms.toml``, one entry per env the zoo has a setting for, :data:`ZOO_ENTRIES`);
``ppo_zoo`` trains on VecNormalize'd observations and rewards (``normalize``, see
:mod:`esa_experiments.training`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from stable_baselines3 import DDPG, PPO, SAC, TD3
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise
from stable_baselines3.common.type_aliases import GymEnv

from esa_experiments.configs import algorithm_hyperparams, lookup
from esa_experiments.param_noise import PPOParamNoise, SACParamNoise


@dataclass(frozen=True)
class Method:
    """A trainable method.

    Attributes:
        label: name in plots and tables.
        family: algorithm family (table name in ``algorithms.toml``).
        addon: ``none``, ``esa``, ``param_noise``, ``ou`` or ``pink``.
        esa: the ESA preset of an ESA method (see :func:`esa_preset`).
        options: further keyword arguments of the ESA drop-in.
        noise_match: an ESA preset whose executed probe TD3's action noise matches in
            variance (:func:`matched_noise_sigma`); empty: the configured ``noise_sigma``.
        config: the table of ``algorithms.toml`` holding its hyperparameters; empty: its
            family's. A table of :data:`ZOO_ENTRIES` has settings for its envs only.
    """

    label: str
    family: str
    addon: str
    esa: str = ""
    options: tuple[tuple[str, Any], ...] = ()
    noise_match: str = ""
    config: str = ""

    @property
    def off_policy(self) -> bool:
        """True for replay-buffer methods (they get smaller step budgets)."""
        return self.family in ("sac", "td3", "ddpg")


METHODS: dict[str, Method] = {
    "ppo": Method("PPO", "ppo", "none"),
    "ppo_esa": Method("PPO+ESA", "ppo", "esa", "default"),
    "ppo_paramnoise": Method("PPO+ParamNoise", "ppo", "param_noise"),
    "ppo_qgrad": Method("PPO+gradient", "ppo", "esa", "default", (("esa_shift", "gradient"),)),
    "ppo_esa_target": Method("PPO+ESA target", "ppo", "esa", "target", (("esa_mode", "target"),)),
    "ppo_qgrad_target": Method(
        "PPO+gradient target",
        "ppo",
        "esa",
        "target",
        (("esa_mode", "target"), ("esa_shift", "gradient")),
    ),
    # Study `seeking_offline` (E1): plain PPO (learning rate 0) fitting each critic ESA probes.
    "ppo_fit_linear": Method("PPO, linear head", "ppo", "esa", "null", (("esa_critic", "linear"),)),
    "ppo_fit_quadratic": Method(
        "PPO, quadratic head", "ppo", "esa", "null", (("esa_critic", "quadratic"),)
    ),
    "ppo_fit_qnet": Method("PPO, Q-network", "ppo", "esa", "null", (("esa_critic", "qnet"),)),
    # Study `seeking` (E2), PPO arms: each critic's ESA, placebo and gradient control, all
    # faded and under the decoupled objective (seeking_ppo); the study sets kappa from E1.
    **{
        f"ppo_seek_{arm}_{critic}": Method(
            f"PPO+{label} ({critic})",
            "ppo",
            "esa",
            "seeking_ppo",
            (("esa_critic", critic), ("esa_objective", "decoupled"), *shift),
        )
        for critic in ("linear", "quadratic", "qnet")
        for arm, label, shift in (
            ("esa", "ESA", ()),
            ("placebo", "placebo", (("esa_shift", "placebo"),)),
            ("qgrad", "gradient", (("esa_shift", "gradient"),)),
        )
    },
    "sac": Method("SAC", "sac", "none"),
    "sac_esa": Method("SAC+ESA", "sac", "esa", "off_policy"),
    "sac_qgrad": Method("SAC+gradient", "sac", "esa", "off_policy", (("esa_shift", "gradient"),)),
    "sac_paramnoise": Method("SAC+ParamNoise", "sac", "param_noise"),
    "td3": Method("TD3", "td3", "none"),
    "td3_esa": Method("TD3+ESA", "td3", "esa", "off_policy"),
    "td3_sine": Method("TD3+sine", "td3", "esa", "sine", (("esa_execute", "probe"),)),
    "td3_qgrad": Method("TD3+gradient", "td3", "esa", "off_policy", (("esa_shift", "gradient"),)),
    "td3_pink": Method("TD3+pink noise", "td3", "pink"),
    "ddpg_ou": Method("DDPG+OU", "ddpg", "ou"),
    # Study `seeking` (E2), off-policy arms: every ESA arm fades (seeking_off_policy).
    **{
        f"{family}_{arm}": Method(
            f"{family.upper()}+{label}", family, "esa", "seeking_off_policy", options
        )
        for family in ("sac", "td3")
        for arm, label, options in (
            ("esa_fade", "ESA (fade)", ()),
            ("placebo", "placebo", (("esa_shift", "placebo"),)),
            ("qgrad_fade", "gradient (fade)", (("esa_shift", "gradient"),)),
            ("mean_esa", "ESA at the mean", (("esa_anchor", "mean"),)),
            (
                "mean_qgrad",
                "gradient at the mean",
                (("esa_anchor", "mean"), ("esa_shift", "gradient")),
            ),
        )
    },
    "td3_gauss_matched": Method(
        "TD3+Gaussian noise (sine's variance)", "td3", "none", noise_match="sine"
    ),
    "td3_pink_matched": Method(
        "TD3+pink noise (sine's variance)", "td3", "pink", noise_match="sine"
    ),
    # Study `zoo_baselines` (E3): the baselines with RL Zoo3's tuned settings.
    "ppo_zoo": Method("PPO (RL Zoo3)", "ppo", "none", config="ppo_zoo"),
    "sac_zoo": Method("SAC (RL Zoo3)", "sac", "none", config="sac_zoo"),
    "td3_zoo": Method("TD3 (RL Zoo3)", "td3", "none", config="td3_zoo"),
    # Study `paper_regime`: E2's quadratic ESA and placebo arms on the zoo's tuned PPO.
    **{
        f"ppo_zoo_seek_{arm}_quadratic": Method(
            f"PPO (RL Zoo3)+{label}",
            "ppo",
            "esa",
            "seeking_ppo",
            (("esa_critic", "quadratic"), ("esa_objective", "decoupled"), *shift),
            config="ppo_zoo",
        )
        for arm, label, shift in (
            ("esa", "ESA", ()),
            ("placebo", "placebo", (("esa_shift", "placebo"),)),
        )
    },
}

LABELS = {name: method.label for name, method in METHODS.items()}
"""Method name -> display name."""

BASELINE_OF = {
    "ppo_esa": "ppo",
    "ppo_qgrad": "ppo",
    "ppo_esa_target": "ppo",
    "ppo_qgrad_target": "ppo",
    "sac_esa": "sac",
    "sac_qgrad": "sac",
    "td3_esa": "td3",
    "td3_sine": "td3",
    "td3_qgrad": "td3",
    "td3_pink": "td3",
    "sac_esa_fade": "sac",
    "sac_placebo": "sac",
    "sac_qgrad_fade": "sac",
    "sac_mean_esa": "sac",
    "sac_mean_qgrad": "sac",
    "td3_esa_fade": "td3",
    "td3_placebo": "td3",
    "td3_qgrad_fade": "td3",
    "td3_mean_esa": "td3",
    "td3_mean_qgrad": "td3",
    "td3_gauss_matched": "td3",
    "td3_pink_matched": "td3",
    "ppo_zoo_seek_esa_quadratic": "ppo_zoo",
    "ppo_zoo_seek_placebo_quadratic": "ppo_zoo",
}
"""Which method an ESA method is compared with (returns and wall-clock overhead)."""


GRADIENT_CONTROL_OF = {
    "ppo_esa": "ppo_qgrad",
    "ppo_esa_target": "ppo_qgrad_target",
    "sac_esa": "sac_qgrad",
    "td3_esa": "td3_qgrad",
    "sac_esa_fade": "sac_qgrad_fade",
    "sac_mean_esa": "sac_mean_qgrad",
    "td3_esa_fade": "td3_qgrad_fade",
    "td3_mean_esa": "td3_mean_qgrad",
}
"""The gradient control of an ESA method: ESC is credited only where it beats it."""

SEEKING_OFF_POLICY_ARMS = {
    "sac": "sac",
    "sac_esa": "sac_esa_fade",
    "sac_placebo": "sac_placebo",
    "sac_qgrad": "sac_qgrad_fade",
    "sac_mean_esa": "sac_mean_esa",
    "sac_mean_qgrad": "sac_mean_qgrad",
    "td3": "td3",
    "td3_esa": "td3_esa_fade",
    "td3_placebo": "td3_placebo",
    "td3_qgrad": "td3_qgrad_fade",
    "td3_mean_esa": "td3_mean_esa",
    "td3_mean_qgrad": "td3_mean_qgrad",
    "td3_sine": "td3_sine",
    "td3_gauss_matched": "td3_gauss_matched",
    "td3_pink_matched": "td3_pink_matched",
}
"""Study ``seeking``'s off-policy arms (the names its runs are stored under) -> method.

``sac_esa``, ``sac_qgrad``, ``td3_esa`` and ``td3_qgrad`` name the confirmation campaign's
unfaded methods, whose finished runs must stay valid: the seeking arms of those names run
the faded ``*_fade`` methods. ``td3_sine`` (unfaded: its sinusoid is the lead the matched
noise arms test) is the arm they match. SAC has no arm executing the sinusoid, so nothing
to match: its exploration is its own entropy-tuned policy, no action noise to widen.
"""

ZOO_ENTRIES = {
    "ppo_zoo": {
        "InvertedPendulum-v5": "InvertedPendulum-v2",
        "InvertedDoublePendulum-v5": "InvertedDoublePendulum-v2",
        "Hopper-v5": "Hopper-v4",
    },
    # The zoo tunes no MuJoCo InvertedDoublePendulum for SAC or TD3: its MuJoCo defaults
    # (the Hopper-v4 entry) are the closest setting it has.
    "sac_zoo": {"InvertedDoublePendulum-v5": "Hopper-v4", "Hopper-v5": "Hopper-v4"},
    "td3_zoo": {"InvertedDoublePendulum-v5": "Hopper-v4", "Hopper-v5": "Hopper-v4"},
}
"""RL Zoo3 arm -> env -> the entry of ``rl_zoo3/hyperparams/<family>.yml`` (RL Zoo3 2.9.2)
whose settings its table in ``algorithms.toml`` holds on that env."""

TARGET_TRUST_REGION = 1.0
TARGET_WEIGHT = 0.03
"""The PPO target mode's bound (policy stds) and loss weight (``target_search``)."""

SEEKING_FADE = 0.5
"""The seeking arms' fade, fixed a priori by study ``seeking``'s rules (not tuned)."""


def seeking_methods(family: str, learner: str) -> dict[str, str]:
    """Study ``seeking``'s candidate arms of ``family`` -> method, for E1's pick ``learner``.

    Args:
        family: ``ppo``, ``sac`` or ``td3``.
        learner: E1's picked learner (``ppo_fit_<critic>`` for PPO, ``sac`` off-policy).

    Raises:
        ValueError: for an unknown family or a learner of another family.
    """
    if family == "ppo":
        critic = learner.removeprefix("ppo_fit_")
        if critic not in ("linear", "quadratic", "qnet") or critic == learner:
            raise ValueError(f"expected a PPO learner ppo_fit_<critic>, got {learner!r}")
        return {f"ppo_{arm}": f"ppo_seek_{arm}_{critic}" for arm in ("esa", "placebo", "qgrad")}
    if family not in ("sac", "td3") or learner != "sac":
        raise ValueError(
            f"expected family sac or td3 with E1's learner 'sac', got {family!r} and {learner!r}"
        )
    return {
        arm: method
        for arm, method in SEEKING_OFF_POLICY_ARMS.items()
        if arm.startswith(f"{family}_") and get_method(method).esa == "seeking_off_policy"
    }


OPTIONAL_FIELDS = ("fade",)
"""``EsaConfig`` fields a run's config holds only when set (None = unset, not stored)."""


def esa_preset(name: str) -> dict[str, Any]:
    """The ``EsaConfig`` fields of an ESA preset (see the module docstring).

    Resolved from ``esa_client`` itself, so a run's fingerprint changes (and the run
    is redone) whenever the shipped default changes.
    """
    from esa_client import EsaConfig

    presets = {
        "default": EsaConfig(),
        "null": EsaConfig(learning_rate=0.0),
        "off_policy": EsaConfig.off_policy(),
        "sine": EsaConfig.off_policy(learning_rate=0.0),
        "target": EsaConfig(trust_region=TARGET_TRUST_REGION),
        "seeking_off_policy": EsaConfig.off_policy(fade=SEEKING_FADE),
        "seeking_ppo": EsaConfig(fade=SEEKING_FADE),
    }
    fields = dataclasses.asdict(lookup(presets, name, "an ESA preset"))
    # OPTIONAL_FIELDS join a run's config only when set: the committed runs' configs lack them,
    # so leaving them out keeps those runs' fingerprints (and with them their results).
    return {k: v for k, v in fields.items() if not (k in OPTIONAL_FIELDS and v is None)}


def matched_noise_sigma(sigma: float, preset: str) -> float:
    """TD3's noise sigma with the variance of TD3 executing ``preset``'s probe.

    ``sqrt(sigma^2 + K^2 / 2)``: per dimension, TD3's Gaussian noise (``sigma``) plus the
    probe's sinusoid of amplitude ``K`` (variance ``K^2 / 2`` over whole periods), which
    ``td3_sine`` executes on top of it. Resolved from the preset, so the matched arms
    follow a change of the shipped amplitude (and their runs are redone).

    Raises:
        ValueError: for a preset whose amplitude is not one number.
    """
    amplitude = esa_preset(preset)["amplitude"]
    if np.ndim(amplitude) != 0:
        raise ValueError(f"expected a scalar amplitude in preset {preset!r}, got {amplitude!r}")
    return math.sqrt(sigma**2 + float(amplitude) ** 2 / 2)


def get_method(name: str) -> Method:
    """Returns the method called ``name``.

    Raises:
        ValueError: for an unknown name (the message lists the known ones).
    """
    return lookup(METHODS, name, "a method")


def resolve_hyperparams(
    method: str, env: str, esa_overrides: dict[str, Any] | None = None
) -> dict[str, Any]:
    """All hyperparameters of ``method`` on ``env``, as stored in the run's sidecar.

    Args:
        method: method name.
        env: task key (selects the per-env tables of the config files).
        esa_overrides: ESA fields replacing those of the method's preset (ablations).

    Raises:
        ValueError: for an RL Zoo3 arm on an env the zoo has no setting for, and for ESA
            overrides of a method without ESA.
    """
    spec = get_method(method)
    entries = ZOO_ENTRIES.get(spec.config)
    if entries is not None and env not in entries:
        raise ValueError(
            f"expected one of {sorted(entries)}, got {env!r} "
            f"(RL Zoo3 has no setting of {method!r} for it)"
        )
    hp = algorithm_hyperparams(spec.config or spec.family, env)
    if spec.noise_match:
        hp["noise_sigma"] = matched_noise_sigma(hp["noise_sigma"], spec.noise_match)
    if spec.addon != "param_noise":
        hp.pop("param_noise", None)
    if spec.addon == "esa":
        hp["esa"] = {**esa_preset(spec.esa), **(esa_overrides or {})}
        hp["esa_options"] = dict(spec.options)
        if spec.esa == "target":
            hp["esa_options"]["esa_target_weight"] = TARGET_WEIGHT
    elif esa_overrides:
        raise ValueError(f"expected ESA overrides only for ESA methods, got them for {method!r}")
    return hp


def _of_family(classes: dict[str, type[BaseAlgorithm]], family: str) -> type[BaseAlgorithm]:
    return classes[family]


def build_model(method: str, env: GymEnv, seed: int, hyperparams: dict[str, Any]) -> BaseAlgorithm:
    """Constructs the SB3 model of ``method`` on ``env`` (CPU, no logging output).

    Args:
        method: method name.
        env: training env (a gymnasium env or an SB3 VecEnv).
        seed: model seed.
        hyperparams: output of :func:`resolve_hyperparams`.
    """
    spec = get_method(method)
    cls: type[BaseAlgorithm]
    hp = dict(hyperparams)
    hp.pop("n_envs", None)  # used to build the env (see training.py)
    hp.pop("normalize", None)  # VecNormalize wraps the env (see training.py)
    kwargs: dict[str, Any] = {
        "policy_kwargs": {"net_arch": hp.pop("net_arch"), **_policy_options(hp)},
        "seed": seed,
        "device": "cpu",
        "verbose": 0,
    }
    if spec.family == "td3":
        kwargs["action_noise"] = _td3_noise(env, spec.addon, hp.pop("noise_sigma"), seed)
    if spec.addon == "esa":
        from esa_client import EsaConfig

        cls, control = esa_class(spec.family, hp.pop("esa_options", {}))
        kwargs["esa"] = EsaConfig(**hp.pop("esa"))
        kwargs["esa_control"] = control
    elif spec.addon == "param_noise":
        cls = _of_family({"ppo": PPOParamNoise, "sac": SACParamNoise}, spec.family)
        kwargs["param_noise"] = hp.pop("param_noise")
    elif spec.addon == "ou":
        dim = int(np.prod(env.action_space.shape or ()))
        kwargs["action_noise"] = OrnsteinUhlenbeckActionNoise(
            mean=np.zeros(dim),
            sigma=hp.pop("ou_sigma") * np.ones(dim),
            theta=hp.pop("ou_theta"),
        )
        cls = DDPG
    else:
        cls = _of_family({"ppo": PPO, "sac": SAC, "td3": TD3}, spec.family)
    return cls("MlpPolicy", env, **kwargs, **hp)


OPTION_DEFAULTS = {
    "esa_critic": "linear",
    "esa_objective": "clip",
    "esa_mode": "behaviour",
    "esa_shift": "esc",
    "esa_anchor": "sample",
    "esa_execute": "shifted",
    "esa_probe_critic": "target_mean",
}
"""The options a run may store (its ``esa_options``), each with the value a run that does not
name it ran with. None of them is an option of the product's drop-ins:
:mod:`esa_experiments.lab` holds each arm as a subclass (:func:`esa_class`)."""


def esa_class(family: str, options: dict[str, Any]) -> tuple[type[BaseAlgorithm], str | None]:
    """The drop-in (or lab subclass) of a run's stored ``esa_options``, and its control.

    Raises:
        ValueError: For an option the studies never had, or an unknown value.
    """
    from esa_experiments.lab.off_policy_arms import off_policy_class
    from esa_experiments.lab.ppo_arms import esappo_class

    unknown = sorted(set(options) - {*OPTION_DEFAULTS, "esa_target_weight"})
    if unknown:
        raise ValueError(f"expected options among {sorted(OPTION_DEFAULTS)}, got {unknown}")
    o = {**OPTION_DEFAULTS, **options}
    shift = o["esa_shift"]
    if shift not in ("esc", "gradient", "placebo"):
        raise ValueError(f"expected esa_shift in ('esc', 'gradient', 'placebo'), got {shift!r}")
    control = None if shift == "esc" else shift
    if family == "ppo":
        ppo = esappo_class(
            o["esa_critic"],
            o["esa_objective"],
            o["esa_mode"],
            float(options.get("esa_target_weight", 1.0)),
        )
        return ppo, control
    arm = off_policy_class(family, o["esa_anchor"], o["esa_execute"], o["esa_probe_critic"])
    return arm, control


def _policy_options(hp: dict[str, Any]) -> dict[str, Any]:
    """The further ``policy_kwargs`` of ``hp`` (popped), the activation named as in torch.nn."""
    options = dict(hp.pop("policy_kwargs", {}))
    if "activation_fn" in options:
        options["activation_fn"] = getattr(torch.nn, options["activation_fn"])
    return options


def _td3_noise(env: GymEnv, addon: str, sigma: float, seed: int) -> Any:
    """TD3's exploration noise: Gaussian, or pink over one episode's length."""
    dim = int(np.prod(env.action_space.shape or ()))
    if addon != "pink":
        return NormalActionNoise(mean=np.zeros(dim), sigma=sigma * np.ones(dim))
    from pink import PinkActionNoise

    spec = env.get_attr("spec")[0] if hasattr(env, "get_attr") else env.spec
    horizon = (spec.max_episode_steps if spec is not None else None) or 1000
    return PinkActionNoise(sigma, horizon, dim, rng=np.random.default_rng(seed))

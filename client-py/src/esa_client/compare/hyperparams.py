"""Hyperparameters in RL Zoo3's format: the zoo's tuned set, or a YAML file of yours.

A zoo file maps env ids to entries; an entry holds the algorithm's keyword arguments plus
the zoo's own keys, which this module turns into what the run needs:

* ``normalize``: ``true`` or a ``"dict(norm_obs=..., norm_reward=...)"`` string:
  ``VecNormalize`` of the training envs;
* ``n_envs``: training envs (default 1); ``n_timesteps``: the default budget;
* ``learning_rate`` / ``clip_range`` ``"lin_<x>"``: a linear schedule from ``x`` to 0;
* ``policy_kwargs``: a ``"dict(...)"`` string (``nn`` is ``torch.nn``), as the zoo evaluates it;
* ``noise_type`` ``normal`` / ``ornstein-uhlenbeck`` with ``noise_std``: action noise (TD3);
* ``esa``: ``EsaConfig`` fields for the ESA arms (the baseline ignores it).

Keys that change the env itself (``env_wrapper``, ``frame_stack``, ``callback``, ...) are
refused: each arm must train on the same env, and a partial reading of the zoo's wrappers
would make a comparison that is not the zoo's. Put the wrapper in a ``module:factory`` env.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

SOURCES = ("auto", "zoo", "default")
"""``--hyperparams`` words; anything else is a path to a zoo-format YAML file."""

_REFUSED = ("env_wrapper", "frame_stack", "callback", "vec_env_wrapper", "env_kwargs")
# The zoo's own keys (how it builds the env and the noise), not the algorithm's arguments.
_ZOO_KEYS = ("normalize", "n_envs", "n_timesteps", "policy", "noise_type", "noise_std")


@dataclass(frozen=True)
class Hyperparams:
    """One algorithm's settings for one env, as the runs use them.

    Attributes:
        source: where they come from (``RL Zoo3 2.9.2 ppo.yml, Hopper-v4``, a file, or SB3's
            defaults).
        kwargs: keyword arguments of the algorithm, in the zoo's notation (JSON-able: the
            rules and the runs' fingerprints hold them).
        policy: the SB3 policy name.
        n_envs: training envs.
        normalize: ``VecNormalize`` keyword arguments, or None for no normalization.
        n_timesteps: the entry's budget, if it has one.
        esa: ``EsaConfig`` fields for the ESA arms.
    """

    source: str
    kwargs: dict[str, Any] = field(default_factory=dict)
    policy: str = "MlpPolicy"
    n_envs: int = 1
    normalize: dict[str, Any] | None = None
    n_timesteps: int | None = None
    esa: dict[str, Any] = field(default_factory=dict)

    def digest(self) -> str:
        """A short hash of everything but the source's wording."""
        payload = json.dumps(
            [self.kwargs, self.policy, self.n_envs, self.normalize, self.esa], sort_keys=True
        )
        return hashlib.sha256(payload.encode()).hexdigest()[:16]


def zoo_file(algo: str) -> Path:
    """RL Zoo3's tuned hyperparameters of ``algo`` (needs the ``zoo`` extra).

    Raises:
        ValueError: if rl_zoo3 is not installed.
    """
    try:
        import rl_zoo3
    except ImportError:
        raise ValueError(
            "expected rl_zoo3 for --hyperparams zoo, got none installed: "
            'pip install "esa-client[zoo]", or pass --hyperparams default or a YAML file'
        ) from None
    return Path(rl_zoo3.__file__).parent / "hyperparams" / f"{algo}.yml"


def _load_yaml(path: Path) -> dict[str, Any]:
    import yaml

    try:
        data = yaml.safe_load(path.read_text())
    except OSError as err:
        raise ValueError(f"expected a readable YAML file, got {path}: {err}") from None
    except yaml.YAMLError as err:
        raise ValueError(f"expected zoo-format YAML in {path}, got a parse error: {err}") from None
    if not isinstance(data, dict):
        raise ValueError(f"expected a mapping of env ids to settings in {path}, got {data!r}")
    return data


def _entry_for(env: str, entries: dict[str, Any]) -> str | None:
    """The entry of ``env``, or of the same env at its newest other version (v5 -> v4)."""
    if env in entries:
        return env
    match = re.fullmatch(r"(.+)-v(\d+)", env)
    if match is None:
        return None
    versions = [
        (int(m.group(1)), key)
        for key in entries
        if (m := re.fullmatch(re.escape(match.group(1)) + r"-v(\d+)", key)) is not None
    ]
    return max(versions)[1] if versions else None


def resolve(source: str, env: str, algo: str) -> Hyperparams:
    """The settings ``--hyperparams source`` gives ``algo`` on ``env``.

    Args:
        source: ``auto`` (the zoo's entry for the env if rl_zoo3 has one, else SB3's
            defaults), ``zoo`` (the zoo's entry, which must exist), ``default`` (SB3's
            defaults), or a zoo-format YAML file with an entry for the env.
        env: the env id (a ``module:factory`` env matches an entry of that exact name).
        algo: ``ppo``, ``sac`` or ``td3``.

    Raises:
        ValueError: a missing entry or file, or an entry this tool cannot apply faithfully.
    """
    if source == "default":
        return Hyperparams("stable-baselines3's defaults")
    if source in ("auto", "zoo"):
        try:
            path = zoo_file(algo)
        except ValueError:
            if source == "zoo":
                raise
            return Hyperparams("stable-baselines3's defaults (rl_zoo3 not installed)")
        import rl_zoo3

        label = f"RL Zoo3 {getattr(rl_zoo3, '__version__', '?')} {algo}.yml"
    else:
        path, label = Path(source), source
    entries = _load_yaml(path)
    key = _entry_for(env, entries)
    if key is None:
        if source == "auto":
            return Hyperparams(f"stable-baselines3's defaults (RL Zoo3 has no {algo} entry)")
        raise ValueError(f"expected an entry for {env!r} in {path}, got entries {sorted(entries)}")
    return parse_entry(entries[key], f"{label}, {key}")


def parse_entry(entry: dict[str, Any], source: str) -> Hyperparams:
    """Turns one zoo entry into :class:`Hyperparams` (see the module docstring)."""
    if not isinstance(entry, dict):
        raise ValueError(f"expected a mapping of settings in {source}, got {entry!r}")
    refused = sorted(set(entry) & set(_REFUSED))
    if refused:
        raise ValueError(
            f"expected no env-changing keys in {source}, got {refused}: wrap the env in a "
            "module:factory passed as --env instead"
        )
    kwargs = {k: v for k, v in entry.items() if k not in _ZOO_KEYS and k != "esa"}
    normalize = entry.get("normalize", False)
    if isinstance(normalize, str):
        normalize = _evaluate(normalize, source)
    elif normalize is True:
        normalize = {}
    elif normalize is False:
        normalize = None
    if "noise_type" in entry:
        kwargs["action_noise"] = {"type": entry["noise_type"], "std": entry.get("noise_std", 0.1)}
    esa = entry.get("esa", {})
    if not isinstance(esa, dict):
        raise ValueError(f"expected esa: to be a mapping of EsaConfig fields, got {esa!r}")
    n_timesteps = entry.get("n_timesteps")
    return Hyperparams(
        source=source,
        kwargs=kwargs,
        policy=str(entry.get("policy", "MlpPolicy")),
        n_envs=int(entry.get("n_envs", 1)),
        normalize=normalize,
        n_timesteps=None if n_timesteps is None else int(n_timesteps),
        esa=dict(esa),
    )


def _evaluate(text: str, source: str) -> Any:
    """Evaluates a zoo ``"dict(...)"`` string with ``nn`` = ``torch.nn``, as the zoo does."""
    from torch import nn

    try:
        return eval(text, {"__builtins__": {}, "dict": dict, "nn": nn})  # noqa: S307
    except Exception as err:
        raise ValueError(
            f"expected a dict(...) expression in {source}, got {text!r}: {err}"
        ) from None


def algorithm_kwargs(params: Hyperparams) -> dict[str, Any]:
    """The keyword arguments of the SB3 constructor, schedules and ``policy_kwargs`` built.

    ``action_noise`` stays a ``{"type", "std"}`` spec: the trainer builds it for the env's
    action space.
    """
    kwargs = dict(params.kwargs)
    for key in ("learning_rate", "clip_range"):
        value = kwargs.get(key)
        if isinstance(value, str) and value.startswith("lin_"):
            kwargs[key] = _linear(float(value[4:]))
    if isinstance(kwargs.get("policy_kwargs"), str):
        kwargs["policy_kwargs"] = _evaluate(kwargs["policy_kwargs"], params.source)
    return kwargs


def _linear(initial: float) -> Any:
    """The zoo's ``lin_<x>``: ``x`` times SB3's remaining progress (1 -> 0)."""

    def schedule(progress_remaining: float) -> float:
        return progress_remaining * initial

    return schedule

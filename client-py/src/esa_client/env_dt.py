"""The control period ``dt`` of an environment: it sets the ESA perturbation phase ``w t dt``."""

from __future__ import annotations

from typing import Any


def _first(env: Any, name: str) -> Any:
    """Reads attribute ``name`` through wrappers, or from env 0 of a vector env (None if none)."""
    try:
        if hasattr(env, "num_envs"):
            # A gymnasium vector wrapper has no get_attr: its unwrapped vector env has.
            vector = env if hasattr(env, "get_attr") else env.unwrapped
            try:
                return vector.get_attr(name, indices=[0])[0]
            except TypeError:
                return vector.get_attr(name)[0]
        return env.get_wrapper_attr(name)
    except AttributeError:
        return None


def env_dt(env: Any, override: float | None = None) -> float:
    """Returns seconds per environment step: ``override``, else ``dt``, else ``1 / render_fps``.

    Args:
        env: A gymnasium environment (possibly wrapped), a gymnasium vector env or an SB3
            ``VecEnv``.
        override: An explicit dt, e.g. ``EsaConfig.dt``.

    Raises:
        ValueError: If none of these gives a positive number.
    """
    if override is not None:
        return float(override)
    dt = _first(env, "dt")
    if isinstance(dt, (int, float)) and dt > 0:
        return float(dt)
    fps = (_first(env, "metadata") or {}).get("render_fps")
    if isinstance(fps, (int, float)) and fps > 0:
        return 1.0 / fps
    raise ValueError(
        "expected the environment to define dt or metadata['render_fps'], got neither; "
        "set EsaConfig(dt=...) to the seconds per environment step"
    )

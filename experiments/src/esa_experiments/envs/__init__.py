"""Gymnasium environments of the reproduction suite: the quadrotor path-tracking task."""

from esa_experiments.envs.quadrotor_env import QuadrotorEnv
from esa_experiments.envs.quadrotor_paths import (
    PATH_NAMES,
    CirclePath,
    ClosedPath,
    EightPath,
    HoverPath,
    TargetPath,
    make_path,
)

__all__ = [
    "PATH_NAMES",
    "CirclePath",
    "ClosedPath",
    "EightPath",
    "HoverPath",
    "QuadrotorEnv",
    "TargetPath",
    "make_path",
]

"""esa_experiments: the ESA reproduction suite and its environments.

Importing the package registers ``esa_experiments/Quadrotor-v0`` with gymnasium, so
``gymnasium.make("esa_experiments/Quadrotor-v0", path="eight")`` works after
``import esa_experiments``; without the import, use the module-prefixed id
``gymnasium.make("esa_experiments:esa_experiments/Quadrotor-v0")``.
"""

import gymnasium

QUADROTOR_ENV_ID = "esa_experiments/Quadrotor-v0"

gymnasium.register(
    id=QUADROTOR_ENV_ID,
    entry_point="esa_experiments.envs.quadrotor_env:QuadrotorEnv",
)

__all__ = ["QUADROTOR_ENV_ID"]

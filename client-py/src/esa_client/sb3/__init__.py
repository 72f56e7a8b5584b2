"""Stable-baselines3 drop-ins: ``ESASAC`` and ``ESAPPO`` take ``esa=EsaConfig(...)``.

Switching a script to ESA is one import and one argument::

    from esa_client.sb3 import ESAPPO, EsaConfig

    model = ESAPPO("MlpPolicy", "InvertedPendulum-v5", esa=EsaConfig(amplitude=0.2))
"""

from ..config import EsaConfig
from .ppo import ESAPPO
from .sac import ESASAC

__all__ = ["ESAPPO", "ESASAC", "EsaConfig"]

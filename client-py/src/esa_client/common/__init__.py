"""Framework-neutral pieces the SB3 drop-ins and the RLlib integration both use.

- :mod:`esa_client.common.runtime`: ``EsaRuntime``, the ESA side of a learner (one
  session per env, one round trip per step, statistics);
- :mod:`esa_client.common.advantage_head`: ESAPPO's critic for ESA (needs torch);
- :mod:`esa_client.common.head_fit_worker`: that critic's fit in a worker process, beside
  the policy's own update.

Neither :mod:`esa_client.sb3` nor :mod:`esa_client.rllib` imports the other; both import
from here (as stable-baselines3's own ``common`` package).
"""

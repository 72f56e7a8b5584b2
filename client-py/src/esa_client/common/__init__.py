"""Framework-neutral pieces the SB3 drop-ins and the RLlib integration both use.

- :mod:`esa_client.common.runtime`: ``EsaRuntime``, the ESA side of a learner;
- :mod:`esa_client.common.quadratic_head`: ESAPPO's critic for ESA (needs torch);
- :mod:`esa_client.common.controls`: the placebo and gradient controls, and what a shift did.

Neither :mod:`esa_client.sb3` nor :mod:`esa_client.rllib` imports the other; both import
from here (as stable-baselines3's own ``common`` package).
"""

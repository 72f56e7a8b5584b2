"""Framework-neutral pieces of the SB3 drop-ins and the RLlib integration, which import neither.

- :mod:`esa_client.common.runtime`: ``EsaRuntime``, the ESA side of a learner;
- :mod:`esa_client.common.quadratic_head`: ESAPPO's critic for ESA (needs torch);
- :mod:`esa_client.common.controls`: the placebo and gradient controls, and what a shift did.
"""

"""A fingerprint of ESAPPO's training: sha256 of the policy's and head's parameters.

Run before and after a performance change; equal digests mean the change kept every
bit (InvertedPendulum-v5, 1 and 8 envs, the shipped EsaConfig() and gate=None, 2
rollouts of 2048 steps after the head's first fit, in-process engine).

Usage::

    python bench/profiles/fingerprint.py
"""

from __future__ import annotations

import hashlib

import torch as th
from run_one import build


def digest(model: object) -> str:
    """sha256 of the policy's and the head's parameters, in order."""
    h = hashlib.sha256()
    for module in (model.policy, model.esa_head):  # type: ignore[attr-defined]
        for p in module.parameters():
            h.update(p.detach().numpy().tobytes())
    h.update(model.rollout_buffer.actions.tobytes())  # type: ignore[attr-defined]
    return h.hexdigest()[:16]


def main() -> None:
    """Prints one digest per setting."""
    th.set_num_threads(1)
    for n_envs in (1, 8):
        for ungated in (False, True):
            model = build("ESAPPO", "inprocess", n_envs, ungated)
            model.learn(4 * 2048)
            model.esa_close()  # type: ignore[attr-defined]
            print(f"n_envs={n_envs} ungated={ungated}: {digest(model)}", flush=True)


if __name__ == "__main__":
    main()

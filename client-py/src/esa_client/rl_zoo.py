"""RL Baselines3 Zoo with ESA: ``esappo``, ``esasac`` and ``esatd3`` as RL Zoo algorithms.

RL Zoo picks its algorithm from ``rl_zoo3.utils.ALGOS`` while it parses the command line, so
the drop-ins are registered there first and the Zoo's own ``train`` / ``enjoy`` run unchanged:
``python -m esa_client.rl_zoo train --algo esappo --env Pendulum-v1`` (``docs/guides/zoo.md``).
"""

from __future__ import annotations

import sys
from importlib import resources
from typing import Any

# algorithm name in the Zoo -> (drop-in class name, the Zoo algorithm whose yaml it defaults to)
ESA_ALGOS: dict[str, tuple[str, str]] = {
    "esappo": ("ESAPPO", "ppo"),
    "esasac": ("ESASAC", "sac"),
    "esatd3": ("ESATD3", "td3"),
}


def register() -> dict[str, Any]:
    """Adds ``esappo``, ``esasac`` and ``esatd3`` to ``rl_zoo3.utils.ALGOS``; returns ALGOS."""
    from rl_zoo3 import utils

    from . import sb3

    for name, (cls, _base) in ESA_ALGOS.items():
        utils.ALGOS[name] = getattr(sb3, cls)
    algos: dict[str, Any] = utils.ALGOS
    return algos


def default_conf(algo: str) -> str | None:
    """The Zoo's hyperparameter file of the algorithm's base, for an ESA algorithm."""
    if algo not in ESA_ALGOS:
        return None
    return str(resources.files("rl_zoo3") / "hyperparams" / f"{ESA_ALGOS[algo][1]}.yml")


def _option(argv: list[str], *names: str) -> str | None:
    for i, arg in enumerate(argv):
        for name in names:
            if arg == name and i + 1 < len(argv):
                return argv[i + 1]
            if arg.startswith(name + "="):
                return arg.split("=", 1)[1]
    return None


def main(argv: list[str] | None = None) -> None:
    """``train ...`` or ``enjoy ...``: RL Zoo's command of that name with the ESA algorithms."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] not in ("train", "enjoy"):
        raise SystemExit(
            "usage: python -m esa_client.rl_zoo {train,enjoy} --algo esappo|esasac|esatd3 ..."
        )
    command, rest = args[0], args[1:]
    register()
    if command == "train":
        algo = _option(rest, "--algo")
        conf = default_conf(algo) if algo is not None else None
        if conf is not None and _option(rest, "-conf", "--conf-file") is None:
            rest = [*rest, "--conf-file", conf]
        from rl_zoo3.train import train as run
    else:
        from rl_zoo3.enjoy import enjoy as run
    sys.argv = [f"rl_zoo3.{command}", *rest]
    run()


if __name__ == "__main__":
    main()

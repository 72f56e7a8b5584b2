"""The ``esa-server`` executable that the esa-server wheel installs, found from Python.

pip puts a wheel's executables into the environment's scripts folder (``bin/`` of a venv),
which need not be on ``PATH``: a venv's Python can run without the venv being activated. So
``esa_client`` asks this package where the executable went instead of searching ``PATH``.
"""

from __future__ import annotations

import sysconfig
from importlib.metadata import PackageNotFoundError, distribution, version
from pathlib import Path

__all__ = ["BINARY_NAME", "__version__", "find_esa_server_bin"]

__version__ = version("esa-server")
BINARY_NAME = "esa-server" + (sysconfig.get_config_var("EXE") or "")


def _installed_copies() -> list[Path]:
    """Where the installer wrote the executable, as its RECORD lists it.

    The RECORD is exact for every layout (a venv, ``--user``, ``--prefix``, ``--target``);
    it is missing only where the installer wrote none.
    """
    try:
        files = distribution("esa-server").files or []
    except PackageNotFoundError:
        return []
    return [Path(str(file.locate())).resolve() for file in files if file.name == BINARY_NAME]


def find_esa_server_bin() -> Path:
    """The path of the installed ``esa-server`` executable.

    Raises:
        FileNotFoundError: If the executable is not where the wheel installed it (removed,
            or an installer that wrote no RECORD and another scripts folder).
    """
    candidates = [*_installed_copies(), Path(sysconfig.get_path("scripts")) / BINARY_NAME]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    searched = "\n".join(f"  {candidate}" for candidate in dict.fromkeys(candidates))
    raise FileNotFoundError(
        f"the esa-server wheel is installed but its executable is missing; looked at:\n"
        f"{searched}\nreinstall it: pip install --force-reinstall esa-server"
    )

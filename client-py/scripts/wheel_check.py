"""The wheel check (`make wheel-check`): the esa-client wheel works on a machine without Rust.

1. builds the wheel with ``make wheel`` (the extension esa_client._native and a bundled
   esa-server), unless ``--wheel`` names one;
2. creates a clean venv in a temporary directory and installs ONLY that wheel, with its
   declared dependencies and the ``sb3`` extra, from the package index (PyPI; the usual
   ``PIP_*`` variables apply);
3. runs ``wheel_user_check.py`` (copied into the temporary directory) with that venv's
   Python in isolated mode, cargo/rustc hidden from PATH, no ``ESA_SERVER_BIN``, and the
   temporary directory as working directory: spawn the sidecar, a SessionBatch against the
   in-process engine, a few hundred ESAPPO and ESASAC steps;
4. prints the wheel's size (and what is in it) and how long each step took.

The install step downloads torch and stable-baselines3 (about 1 GB to several GB with
torch's CUDA libraries), so this check is not part of ``make test``.

Usage: python client-py/scripts/wheel_check.py [--wheel PATH] [--python PY] [--keep]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
USER_CHECK = Path(__file__).with_name("wheel_user_check.py")
# What the user's environment must not have: a Rust toolchain or a server on PATH.
HIDDEN_TOOLS = ("cargo", "rustc", "rustup", "esa-server")
# Variables that would point the user's Python at the checkout or at another server.
DROPPED_VARS = ("ESA_SERVER_BIN", "PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "CARGO_TARGET_DIR")


def run(command: list[str], **kwargs: object) -> float:
    """Runs ``command`` (failing on a non-zero exit); returns its wall-clock seconds."""
    print("$", " ".join(command), flush=True)
    start = time.perf_counter()
    subprocess.run(command, check=True, **kwargs)  # type: ignore[call-overload]
    return time.perf_counter() - start


def newest_wheel() -> Path:
    wheels = sorted((REPO_ROOT / "dist").glob("esa_client-*.whl"), key=lambda p: p.stat().st_mtime)
    if not wheels:
        raise SystemExit(f"no esa_client wheel in {REPO_ROOT / 'dist'}: run `make wheel`")
    return wheels[-1]


def wheel_contents(wheel: Path) -> dict[str, object]:
    """Sizes of the wheel and of its two binaries; fails if the server is missing."""
    with zipfile.ZipFile(wheel) as archive:
        infos = {info.filename: info for info in archive.infolist()}
    server = infos.get("esa_client/_bin/esa-server")
    if server is None:
        raise SystemExit(f"{wheel.name} bundles no esa_client/_bin/esa-server")
    if not (server.external_attr >> 16) & 0o111:
        raise SystemExit(f"{wheel.name}: esa_client/_bin/esa-server has no executable mode")
    native = next(info for name, info in infos.items() if name.startswith("esa_client/_native"))
    return {
        "wheel": wheel.name,
        "wheel_bytes": wheel.stat().st_size,
        "esa-server_bytes": server.file_size,
        "esa-server_compressed_bytes": server.compress_size,
        "_native_bytes": native.file_size,
        "files": len(infos),
    }


def user_environment(venv: Path) -> dict[str, str]:
    """The environment of a user without Rust: PATH without cargo and friends, no overrides."""
    keep = []
    for entry in os.environ.get("PATH", "").split(os.pathsep):
        if entry and not any((Path(entry) / tool).exists() for tool in HIDDEN_TOOLS):
            keep.append(entry)
    env = {k: v for k, v in os.environ.items() if k not in DROPPED_VARS}
    env["PATH"] = os.pathsep.join([str(venv / "bin"), *keep])
    env["PYTHONNOUSERSITE"] = "1"
    return env


def du(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file() and not f.is_symlink())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--wheel", type=Path, help="check this wheel instead of building one")
    parser.add_argument(
        "--python", default=sys.executable, help="interpreter the clean venv is made from"
    )
    parser.add_argument("--keep", action="store_true", help="keep the temporary directory")
    args = parser.parse_args()

    seconds: dict[str, float] = {}
    start = time.perf_counter()
    if args.wheel is None:
        seconds["make wheel"] = run(["make", "wheel"], cwd=REPO_ROOT)
        wheel = newest_wheel()
    else:
        wheel = args.wheel.resolve()
    contents = wheel_contents(wheel)

    tmp = Path(tempfile.mkdtemp(prefix="esa-wheel-check-"))
    try:
        venv, work = tmp / "venv", tmp / "work"
        work.mkdir()
        seconds["create venv"] = run([args.python, "-m", "venv", str(venv)], cwd=tmp)
        python = str(venv / "bin" / "python")
        env = user_environment(venv)
        seconds["pip install wheel[sb3]"] = run(
            [python, "-m", "pip", "install", "--quiet", f"{wheel}[sb3]"], cwd=work, env=env
        )
        installed = du(venv)
        script = shutil.copy(USER_CHECK, work / USER_CHECK.name)
        out = work / "user_check.json"
        seconds["user script"] = run(
            [python, "-I", str(script), str(REPO_ROOT), str(out)], cwd=work, env=env
        )
        user = json.loads(out.read_text())
    finally:
        if args.keep:
            print(f"kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    seconds["total"] = time.perf_counter() - start

    report = {
        **contents,
        "venv_bytes_after_install": installed,
        "seconds": {name: round(value, 1) for name, value in seconds.items()},
        "user_check": user,
    }
    print("\nwheel check passed:")
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()

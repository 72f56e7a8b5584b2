"""The wheel check (`make wheel-check`): the esa wheels work on a machine without Rust.

1. builds the wheels with ``make wheel`` (esa-client: esa_client and its extension;
   esa-server: the server executable), unless ``--no-build`` takes dist/'s newest;
2. checks what is in them: no server in the client wheel, an executable in the server wheel,
   and the client's ``server`` extra pinning exactly the built server's version;
3. creates a clean venv in a temporary directory and installs ONLY the client wheel with the
   ``sb3`` extra, its dependencies from the package index (PyPI; the usual ``PIP_*``
   variables apply). There, with cargo/rustc hidden from PATH, no ``ESA_SERVER_BIN`` and the
   temporary directory as working directory, it runs README.md's first Python snippet as
   pasted and ``wheel_user_check.py client`` (in-process, and the missing server's error);
4. installs the ``server`` extra from the built server wheel into the same venv and runs
   ``wheel_user_check.py server`` (the server wheel spawned, and the drop-ins on it);
5. installs the ``compare`` extra and runs ``esa-compare`` on MountainCarContinuous-v0, an
   env no test or study of ours uses: it must write the curves and the verdict, and the
   same command again must do nothing;
6. prints the wheels' sizes and how long each step took.

The install step downloads torch and stable-baselines3 (about 1 GB to several GB with
torch's CUDA libraries), so this check is not part of ``make test``.

Usage: python client-py/scripts/wheel_check.py [--no-build] [--python PY] [--keep]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
DIST = REPO_ROOT / "dist"
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


def newest(pattern: str) -> Path:
    found = sorted(DIST.glob(pattern), key=lambda p: p.stat().st_mtime)
    if not found:
        raise SystemExit(f"no {pattern} in {DIST}: run `make wheel`")
    return found[-1]


def version_of(wheel: Path) -> str:
    return wheel.name.split("-")[1]


def check_contents(client: Path, server: Path) -> dict[str, object]:
    """What the two wheels hold; fails where a user would get the wrong thing."""
    with zipfile.ZipFile(client) as archive:
        client_files = {info.filename: info for info in archive.infolist()}
        metadata_name = next(n for n in client_files if n.endswith(".dist-info/METADATA"))
        metadata = archive.read(metadata_name).decode()
    with zipfile.ZipFile(server) as archive:
        server_files = {info.filename: info for info in archive.infolist()}
    bundled = [name for name in client_files if Path(name).name.startswith("esa-server")]
    if bundled:
        raise SystemExit(f"{client.name} carries a server: {bundled}")
    native = next(info for name, info in client_files.items() if "/_native" in name)
    executable = f"esa_server-{version_of(server)}.data/scripts/esa-server"
    binary = server_files.get(executable)
    if binary is None:
        raise SystemExit(f"{server.name} has no {executable}")
    if not (binary.external_attr >> 16) & 0o111:
        raise SystemExit(f"{server.name}: {executable} has no executable mode")
    pins = re.findall(r"^Requires-Dist: esa-server==(\S+) ?; extra == .server.$", metadata, re.M)
    if pins != [version_of(server)]:
        raise SystemExit(
            f"{client.name}'s server extra pins esa-server {pins}, the built server is "
            f"{version_of(server)}: set client-py/pyproject.toml's extra to the Cargo version"
        )
    return {
        "client_wheel": client.name,
        "client_wheel_bytes": client.stat().st_size,
        "_native_bytes": native.file_size,
        "server_wheel": server.name,
        "server_wheel_bytes": server.stat().st_size,
        "esa-server_bytes": binary.file_size,
    }


def readme_snippet() -> str:
    """README.md's first Python code block, exactly as a user would paste it."""
    match = re.search(r"^```python\n(.*?)^```", (REPO_ROOT / "README.md").read_text(), re.S | re.M)
    if match is None:
        raise SystemExit("README.md has no ```python block")
    return match.group(1)


def user_environment(venv: Path) -> dict[str, str]:
    """The environment of a user without Rust: PATH without cargo and friends, no overrides."""
    keep = []
    for entry in os.environ.get("PATH", "").split(os.pathsep):
        if entry and not any((Path(entry) / tool).exists() for tool in HIDDEN_TOOLS):
            keep.append(entry)
    env = {k: v for k, v in os.environ.items() if k not in DROPPED_VARS}
    env["PATH"] = os.pathsep.join([str(venv / "bin"), *keep])
    env["PYTHONNOUSERSITE"] = "1"
    # torch's OpenMP threads wait for each other on a busy machine (SAC's steps took 10x as
    # long with 2 threads on 2 shared cores): this checks the packages, not their speed.
    env.setdefault("OMP_NUM_THREADS", "1")
    return env


def du(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file() and not f.is_symlink())


COMPARE_ARGS = [
    "--env", "MountainCarContinuous-v0", "--algo", "ppo", "--hyperparams", "default",
    "--seeds", "2", "--steps", "2048", "--eval-every", "1024", "--eval-episodes", "1",
    "--out", "compare", "--jobs", "2",
]  # fmt: skip
"""A tiny comparison on an env that no test or study of ours uses."""


def compare_check(venv: Path, work: Path, env: dict[str, str]) -> float:
    """Runs ``esa-compare`` twice: the first writes the verdict, the second does nothing."""
    command = [str(venv / "bin" / "esa-compare"), *COMPARE_ARGS]
    seconds = run(command, cwd=work, env=env)
    folder = work / "compare"
    for name in ("learning_curves.png", "verdicts.md", "RESULTS.md", "provenance.json"):
        if not (folder / name).is_file():
            raise SystemExit(f"esa-compare wrote no {name} in {folder}")
    again = subprocess.run(command, cwd=work, env=env, check=True, capture_output=True, text=True)
    if "Nothing to do" not in again.stdout:
        raise SystemExit(f"expected the second esa-compare to do nothing, got:\n{again.stdout}")
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--no-build", action="store_true", help="check dist/'s newest wheels")
    parser.add_argument(
        "--python", default=sys.executable, help="interpreter the clean venv is made from"
    )
    parser.add_argument("--keep", action="store_true", help="keep the temporary directory")
    args = parser.parse_args()

    seconds: dict[str, float] = {}
    start = time.perf_counter()
    if not args.no_build:
        seconds["make wheel"] = run(["make", "wheel"], cwd=REPO_ROOT)
    client, server = newest("esa_client-*.whl"), newest("esa_server-*.whl")
    contents = check_contents(client, server)

    tmp = Path(tempfile.mkdtemp(prefix="esa-wheel-check-"))
    user: dict[str, object] = {}
    try:
        venv, work = tmp / "venv", tmp / "work"
        work.mkdir()
        seconds["create venv"] = run([args.python, "-m", "venv", str(venv)], cwd=tmp)
        python = str(venv / "bin" / "python")
        env = user_environment(venv)
        pip = [python, "-m", "pip", "install", "--quiet"]
        seconds["pip install esa-client[sb3]"] = run([*pip, f"{client}[sb3]"], cwd=work, env=env)
        installed = du(venv)
        script = shutil.copy(USER_CHECK, work / USER_CHECK.name)
        snippet = work / "readme_snippet.py"
        snippet.write_text(readme_snippet())
        seconds["README snippet"] = run([python, "-I", str(snippet)], cwd=work, env=env)
        for stage in ("client", "server"):
            if stage == "server":
                # The server extra resolved against the built server wheel, not the index.
                install = [*pip, f"{client}[sb3,server]", str(server)]
                seconds["pip install esa-client[sb3,server]"] = run(install, cwd=work, env=env)
            out = work / f"user_check_{stage}.json"
            command = [python, "-I", str(script), stage, str(REPO_ROOT), str(out)]
            seconds[f"user script ({stage})"] = run(command, cwd=work, env=env)
            user[stage] = json.loads(out.read_text())
        seconds["pip install esa-client[compare]"] = run(
            [*pip, f"{client}[compare]"], cwd=work, env=env
        )
        seconds["esa-compare"] = compare_check(venv, work, env)
    finally:
        if args.keep:
            print(f"kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    seconds["total"] = time.perf_counter() - start

    report = {
        **contents,
        "venv_bytes_after_sb3_install": installed,
        "seconds": {name: round(value, 1) for name, value in seconds.items()},
        "user_check": user,
    }
    print("\nwheel check passed:")
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()

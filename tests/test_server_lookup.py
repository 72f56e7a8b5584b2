"""The one esa-server lookup (esa_client.sidecar.find_server_binary) and its order.

Fake executables stand in for the servers: the lookup only checks that a file is
executable, it does not run it (except the cargo build, which these tests disable).
"""

import os
import sys
import types
from pathlib import Path

import pytest
from esa_client import EsaError, sidecar
from esa_client.sidecar import BINARY_ENV, find_server_binary, server_wheel_binary


def fake_executable(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("#!/bin/sh\nexit 0\n")
    path.chmod(0o755)
    return path


def fake_checkout(root: Path, built: bool = True) -> Path:
    (root / "server").mkdir(parents=True)
    (root / "server" / "Cargo.toml").write_text('[package]\nname = "esa-server"\n')
    if built:
        fake_executable(root / "target" / "release" / "esa-server")
    return root


@pytest.fixture
def isolated(tmp_path, monkeypatch):
    """No env var, nothing on PATH, esa_client imported from a wheel, no esa-server wheel.

    Returns the scripts folder where :func:`server_wheel` installs the esa-server wheel.
    """
    monkeypatch.delenv(BINARY_ENV, raising=False)
    monkeypatch.delenv("CARGO_TARGET_DIR", raising=False)
    empty = tmp_path / "empty-path"
    empty.mkdir()
    monkeypatch.setenv("PATH", str(empty))
    # sidecar.py of a wheel install: parents[3] is no checkout.
    monkeypatch.setattr(sidecar, "_REPO_ROOT", tmp_path / "site-packages")
    # None in sys.modules makes `import esa_server` raise ImportError: not installed.
    monkeypatch.setitem(sys.modules, "esa_server", None)
    return tmp_path / "venv" / "bin"


@pytest.fixture
def server_wheel(isolated, monkeypatch):
    """Installs a fake esa-server wheel: its package finds the executable in ``isolated``."""

    def install(executable=True):
        path = fake_executable(isolated / "esa-server")
        if not executable:
            path.chmod(0o644)
        package = types.ModuleType("esa_server")

        def find_esa_server_bin():
            if not path.is_file():
                raise FileNotFoundError(f"looked at {path}")
            return path

        package.find_esa_server_bin = find_esa_server_bin
        monkeypatch.setitem(sys.modules, "esa_server", package)
        return path

    return install


def test_env_var_wins_over_the_server_wheel(server_wheel, tmp_path, monkeypatch):
    server_wheel()
    chosen = fake_executable(tmp_path / "mine" / "esa-server")
    monkeypatch.setenv(BINARY_ENV, str(chosen))
    assert find_server_binary() == chosen
    # An explicit argument wins over both.
    other = fake_executable(tmp_path / "other" / "esa-server")
    assert find_server_binary(other) == other


def test_a_broken_env_var_is_an_error_not_skipped(server_wheel, tmp_path, monkeypatch):
    server_wheel()
    monkeypatch.setenv(BINARY_ENV, str(tmp_path / "missing"))
    with pytest.raises(EsaError, match="expected an executable esa-server"):
        find_server_binary()


def test_the_server_wheel_wins_over_a_checkout_and_path(server_wheel, tmp_path):
    installed = server_wheel()
    checkout = fake_checkout(tmp_path / "repo")
    fake_executable(tmp_path / "empty-path" / "esa-server")
    assert server_wheel_binary() == installed
    assert find_server_binary(checkout=checkout, build=False) == installed


def test_a_checkout_build_wins_over_path(isolated, tmp_path):
    checkout = fake_checkout(tmp_path / "repo")
    fake_executable(tmp_path / "empty-path" / "esa-server")
    found = find_server_binary(checkout=checkout, build=False)
    assert found == checkout / "target" / "release" / "esa-server"


def test_cargo_target_dir_is_honoured(isolated, tmp_path, monkeypatch):
    checkout = fake_checkout(tmp_path / "repo", built=False)
    elsewhere = fake_executable(tmp_path / "targets" / "release" / "esa-server")
    monkeypatch.setenv("CARGO_TARGET_DIR", str(tmp_path / "targets"))
    assert find_server_binary(checkout=checkout, build=False) == elsewhere


def test_path_is_the_last_resort(isolated, tmp_path):
    unbuilt = fake_checkout(tmp_path / "repo", built=False)
    on_path = fake_executable(tmp_path / "empty-path" / "esa-server")
    assert find_server_binary(checkout=unbuilt, build=False) == on_path


def test_nothing_found_says_how_to_get_one(isolated, tmp_path):
    unbuilt = fake_checkout(tmp_path / "repo", built=False)
    with pytest.raises(EsaError, match="cannot find esa-server") as info:
        find_server_binary(checkout=unbuilt, build=False)
    message = str(info.value)
    assert 'pip install "esa-client[server]"' in message
    assert (
        BINARY_ENV in message and str(unbuilt) in message and "cargo build" in message
    )
    # Outside any checkout the build hint still names the command.
    with pytest.raises(EsaError, match="cargo build --release -p esa-server"):
        find_server_binary(build=False)


def test_an_editable_install_ignores_the_server_wheel(
    server_wheel, tmp_path, monkeypatch
):
    # esa_client imported from a checkout: the checkout's build belongs to it, a server wheel
    # in the same environment may be of another version.
    checkout = fake_checkout(tmp_path / "repo")
    server_wheel()
    monkeypatch.setattr(sidecar, "_REPO_ROOT", checkout)
    assert server_wheel_binary() is None
    assert (
        find_server_binary(build=False)
        == checkout / "target" / "release" / "esa-server"
    )


def test_a_server_wheel_without_its_mode_is_a_clear_error(server_wheel):
    installed = server_wheel(executable=False)
    if os.access(installed, os.X_OK):  # root may execute anything
        pytest.skip("this user can execute files without the x bit")
    with pytest.raises(EsaError, match="not executable"):
        find_server_binary()


def test_a_server_wheel_that_lost_its_executable_says_so(server_wheel):
    server_wheel().unlink()
    with pytest.raises(EsaError, match="looked at"):
        find_server_binary()

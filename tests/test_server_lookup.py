"""The one esa-server lookup (esa_client.sidecar.find_server_binary) and its order.

Fake executables stand in for the servers: the lookup only checks that a file is
executable, it does not run it (except the cargo build, which these tests disable).
"""

import os
from pathlib import Path

import pytest
from esa_client import EsaError, sidecar
from esa_client.sidecar import BINARY_ENV, bundled_server_binary, find_server_binary


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
    """No env var, nothing on PATH, esa_client imported from a wheel (_bin here)."""
    monkeypatch.delenv(BINARY_ENV, raising=False)
    monkeypatch.delenv("CARGO_TARGET_DIR", raising=False)
    empty = tmp_path / "empty-path"
    empty.mkdir()
    monkeypatch.setenv("PATH", str(empty))
    package = tmp_path / "site-packages" / "esa_client"
    package.mkdir(parents=True)
    # sidecar.py of a wheel install: parents[3] is no checkout.
    monkeypatch.setattr(sidecar, "_REPO_ROOT", tmp_path / "site-packages")
    monkeypatch.setattr(sidecar.resources, "files", lambda name: package)
    return package


def test_env_var_wins_over_the_bundled_server(isolated, tmp_path, monkeypatch):
    fake_executable(isolated / "_bin" / "esa-server")
    chosen = fake_executable(tmp_path / "mine" / "esa-server")
    monkeypatch.setenv(BINARY_ENV, str(chosen))
    assert find_server_binary() == chosen
    # An explicit argument wins over both.
    other = fake_executable(tmp_path / "other" / "esa-server")
    assert find_server_binary(other) == other


def test_a_broken_env_var_is_an_error_not_skipped(isolated, tmp_path, monkeypatch):
    fake_executable(isolated / "_bin" / "esa-server")
    monkeypatch.setenv(BINARY_ENV, str(tmp_path / "missing"))
    with pytest.raises(EsaError, match="expected an executable esa-server"):
        find_server_binary()


def test_the_bundled_server_wins_over_a_checkout_and_path(isolated, tmp_path):
    bundled = fake_executable(isolated / "_bin" / "esa-server")
    checkout = fake_checkout(tmp_path / "repo")
    fake_executable(tmp_path / "empty-path" / "esa-server")
    assert bundled_server_binary() == bundled
    assert find_server_binary(checkout=checkout, build=False) == bundled


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
    assert "make wheel" in message and BINARY_ENV in message and str(unbuilt) in message


def test_an_editable_install_ignores_a_leftover_bin_folder(
    isolated, tmp_path, monkeypatch
):
    # esa_client imported from a checkout: src/esa_client/_bin is what an interrupted
    # `make wheel` left behind, not a bundled server; the checkout's build is used.
    checkout = fake_checkout(tmp_path / "repo")
    fake_executable(isolated / "_bin" / "esa-server")
    monkeypatch.setattr(sidecar, "_REPO_ROOT", checkout)
    assert bundled_server_binary() is None
    assert (
        find_server_binary(build=False)
        == checkout / "target" / "release" / "esa-server"
    )


def test_a_bundled_server_without_its_mode_is_a_clear_error(isolated):
    bundled = fake_executable(isolated / "_bin" / "esa-server")
    bundled.chmod(0o644)
    if os.access(bundled, os.X_OK):  # root may execute anything
        pytest.skip("this user can execute files without the x bit")
    with pytest.raises(EsaError, match="not executable"):
        find_server_binary()

"""Finding, starting and stopping a private ``esa-server`` process (used by ``EsaClient.spawn``)."""

from __future__ import annotations

import json
import logging
import numbers
import os
import shutil
import signal
import subprocess
import tempfile
import time
import weakref
from collections.abc import Sequence
from pathlib import Path

from .errors import EsaError, ServerUnavailable, StatusCode

logger = logging.getLogger(__name__)

BINARY_ENV = "ESA_SERVER_BIN"
BINARY_NAME = "esa-server"
# src/esa_client/sidecar.py -> repository root (only in a source checkout).
_REPO_ROOT = Path(__file__).resolve().parents[3]
_STDERR_TAIL = 2000


def _cargo_build(repo: Path) -> Path:
    """Builds ``esa-server`` in release mode and returns the path cargo reports."""
    logger.info("building %s with cargo in %s (first use may take minutes)", BINARY_NAME, repo)
    command = ["cargo", "build", "--release", "-p", BINARY_NAME, "--message-format=json"]
    result = subprocess.run(command, cwd=repo, capture_output=True, text=True, check=False)
    if result.returncode != 0:
        raise EsaError(f"`{' '.join(command)}` failed in {repo}:\n{result.stderr[-_STDERR_TAIL:]}")
    for line in result.stdout.splitlines():
        message = json.loads(line) if line.startswith("{") else {}
        if message.get("target", {}).get("name") == BINARY_NAME and message.get("executable"):
            return Path(message["executable"])
    raise EsaError(f"cargo built no {BINARY_NAME} executable in {repo}")


def _is_checkout(path: Path | None) -> bool:
    """True if ``path`` is the root of a source checkout of the esa repository."""
    return path is not None and (path / "server" / "Cargo.toml").is_file()


def _executable(path: Path) -> bool:
    return path.is_file() and os.access(path, os.X_OK)


def server_wheel_binary() -> Path | None:
    """The ``esa-server`` of the installed esa-server wheel, or None (also in a source checkout).

    Raises:
        EsaError: If the wheel's executable is missing or not executable, saying how to repair it.
    """
    if _is_checkout(_REPO_ROOT):
        return None
    try:
        from esa_server import find_esa_server_bin
    except ImportError:
        return None
    try:
        path = find_esa_server_bin()
    except FileNotFoundError as error:
        raise EsaError(str(error)) from None
    if not os.access(path, os.X_OK):
        raise EsaError(
            f"the esa-server wheel's {path} is not executable: `chmod +x` it, "
            f"or set {BINARY_ENV} to another esa-server"
        )
    return path


def find_server_binary(
    binary: str | os.PathLike[str] | None = None,
    *,
    checkout: str | os.PathLike[str] | None = None,
    build: bool = True,
) -> Path:
    """Locates the ``esa-server`` executable, in the order docs/install.md gives.

    Args:
        binary: Path of the executable; None searches.
        checkout: A source checkout to look in before the one esa_client is imported from.
        build: Whether a checkout's server may be built; False only takes an existing build.

    Raises:
        EsaError: If none is found, the explicit one is not executable, or the build fails.
    """
    explicit = binary if binary is not None else os.environ.get(BINARY_ENV)
    if explicit:
        path = Path(explicit)
        if not _executable(path):
            raise EsaError(f"expected an executable esa-server at {path}, got none")
        return path
    if (from_wheel := server_wheel_binary()) is not None:
        return from_wheel
    roots = [Path(checkout)] if checkout is not None else []
    repo = next((root for root in [*roots, _REPO_ROOT] if _is_checkout(root)), None)
    if repo is not None:
        if build and shutil.which("cargo"):
            return _cargo_build(repo)
        target_dir = Path(os.environ.get("CARGO_TARGET_DIR") or "target")
        built = repo / target_dir / "release" / BINARY_NAME  # an absolute target_dir wins
        if _executable(built):
            return built
    if on_path := shutil.which(BINARY_NAME):
        return Path(on_path)
    build_hint = (
        f"build it in {repo} with `cargo build --release -p {BINARY_NAME}` (or `make build`)"
        if repo is not None
        else f"build it from a clone with `cargo build --release -p {BINARY_NAME}`"
    )
    raise EsaError(
        f"cannot find {BINARY_NAME}, which EsaClient.spawn() and the sidecar engine start "
        f"(EsaClient.in_process() and a running server's EsaClient.connect() need none): "
        f'install it with `pip install "esa-client[server]"`, set {BINARY_ENV} to its path, '
        f"or {build_hint}"
    )


def limit_args(
    session_ttl: float | None, max_sessions: int | None, max_session_memory: int | None
) -> list[str]:
    """The server's flags of these limits (``EsaClient.spawn``'s); None leaves one out.

    Raises:
        ValueError: If a limit is not a number at least its minimum.
    """
    args: list[str] = []
    limits: list[tuple[str, object, int, bool]] = [
        ("session_ttl", session_ttl, 0, False),
        ("max_sessions", max_sessions, 1, True),
        ("max_session_memory", max_session_memory, 1, True),
    ]
    for name, value, minimum, integral in limits:
        if value is None:
            continue
        kind = numbers.Integral if integral else numbers.Real
        if isinstance(value, bool) or not isinstance(value, kind) or not float(value) >= minimum:
            what = "an integer" if integral else "a number"
            raise ValueError(f"expected {name} to be {what} >= {minimum} or None, got {value!r}")
        args += [f"--{name.replace('_', '-')}", str(value)]
    return args


def _terminate(process: subprocess.Popen[bytes], workdir: Path, grace: float) -> None:
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=grace)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    shutil.rmtree(workdir, ignore_errors=True)


class ServerProcess:
    """A running ``esa-server`` child process listening on a private Unix socket.

    :meth:`stop` or exit removes the socket's temporary directory; if this process is killed,
    the server follows it (``--parent-pid``) and removes it itself.
    """

    def __init__(
        self,
        binary: str | os.PathLike[str] | None = None,
        *,
        token: str | None = None,
        extra_args: Sequence[str] = (),
        stop_grace: float = 5.0,
    ) -> None:
        """Starts the server.

        Args:
            binary: Path of the executable; None searches for it (:func:`find_server_binary`).
            token: An auth token the server will require; None = no token.
            extra_args: More command-line arguments (e.g. :func:`limit_args`).
            stop_grace: Seconds to wait after SIGTERM before SIGKILL.

        Raises:
            ValueError: If the token is empty.
        """
        if token is not None and not token.strip():
            raise ValueError(f"expected a non-empty token or None, got {token!r}")
        self.binary = find_server_binary(binary)
        self.token = token
        self._workdir = Path(tempfile.mkdtemp(prefix="esa-server-"))
        self.socket_path = self._workdir / "esa.sock"
        self.address = f"unix:{self.socket_path}"
        self._log_path = self._workdir / "server.log"
        args = [str(self.binary), "--uds", str(self.socket_path)]
        # Whatever ends this process, the server follows and cleans up after itself.
        args += ["--parent-pid", str(os.getpid()), "--remove-dir-on-exit", str(self._workdir)]
        if token is not None:
            token_path = self._workdir / "token"
            token_path.touch(mode=0o600)
            token_path.write_text(token)
            args += ["--auth-token-file", str(token_path)]
        args += list(extra_args)
        with open(self._log_path, "wb") as log:
            # Plain log lines: their tail ends up in Python error messages.
            env = {**os.environ, "NO_COLOR": "1"}
            try:
                self._process = subprocess.Popen(
                    args, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, env=env
                )
            except OSError as err:
                shutil.rmtree(self._workdir, ignore_errors=True)
                raise EsaError(f"cannot start {self.binary}: {err}") from err
        self._finalizer = weakref.finalize(
            self, _terminate, self._process, self._workdir, stop_grace
        )
        logger.debug("started %s (pid %d) on %s", self.binary, self._process.pid, self.address)

    @property
    def pid(self) -> int:
        """The server's process id."""
        return self._process.pid

    def running(self) -> bool:
        """True while the process has not exited."""
        return self._process.poll() is None

    def _output(self) -> str:
        try:
            return self._log_path.read_text(errors="replace")
        except OSError:
            return ""

    def output_tail(self) -> str:
        """The last lines the server wrote to stdout/stderr."""
        return self._output()[-_STDERR_TAIL:].strip() or "(no server output)"

    def announced(self, prefix: str, timeout: float) -> list[str]:
        """Waits for the ``listening on`` line; returns what follows ``prefix`` in earlier lines.

        Raises:
            ServerUnavailable: If the server exits or does not get there within ``timeout`` s.
        """
        deadline = time.monotonic() + timeout
        while True:
            self.check_running()
            lines = self._output().splitlines()
            if any(line.startswith("listening on ") for line in lines):
                return [line[len(prefix) :] for line in lines if line.startswith(prefix)]
            if time.monotonic() > deadline:
                raise ServerUnavailable(
                    f"{self.binary} printed no `listening on` line within {timeout} s; "
                    f"its output:\n{self.output_tail()}",
                    StatusCode.UNAVAILABLE,
                )
            # The output goes to a file (so that it never blocks the server): poll it.
            time.sleep(0.01)

    def check_running(self) -> None:
        """Raises ``ServerUnavailable`` with the server's output if it has exited."""
        code = self._process.poll()
        if code is not None:
            raise ServerUnavailable(
                f"{self.binary} exited with code {code}; its output:\n{self.output_tail()}",
                StatusCode.UNAVAILABLE,
            )

    def stop(self) -> None:
        """Stops the server (SIGTERM, then SIGKILL) and removes its socket directory."""
        self._finalizer()

"""Where the env runners' ESA sessions live: one sidecar per node, or a given server.

By default (``EsaService()``) every EnvRunner uses its node's sidecar: one
``esa-server`` per node and user, on a Unix socket in a private directory, started by
the first runner of the node that needs it and shared by all the others (every env
runner process, of every Ray job of this user on that node). :class:`NodeSidecar` is a
runner's hold on it:

- Starting is serialized by an exclusive ``flock`` on ``DIR/start.lock``: a runner takes
  it, then joins as a user (a shared ``flock`` on ``DIR/users.lock``, kept for as long as
  the runner lives), then reads ``DIR/server.json``. If no live server is recorded
  there, it starts the keeper (``_keeper.py``, a stdlib-only process in its own session,
  so it outlives the runner that started it) and waits for the keeper to record the
  server before it lets ``start.lock`` go. Two runners starting at once thus get one
  server: the second blocks on ``start.lock`` and then finds the first one's.
- The keeper stops the server once nobody holds ``users.lock`` and nobody is joining
  (it takes both locks exclusively, without blocking). A runner that dies, however it
  dies, drops its shared lock with its last file descriptor, so the sidecar ends a
  moment (``_keeper.POLL_SECONDS``) after the node's last runner.

Or ``EsaService(address="host:port")`` (or ``"unix:/path"``) for a shared server over
gRPC, ``EsaService(zenoh="tcp/host:7447")`` for one over Zenoh, and
``EsaService(zenoh=..., shards=N)`` for N servers started with ``--shard i/N``
(``deploy/README.md``).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import stat
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

from .._proto.esa.v1 import esa_pb2
from ..client import EsaClient
from ..common.runtime import OnUnavailable, check_on_unavailable
from ..errors import EsaError, ServerUnavailable, StatusCode
from ..reconnect import DEFAULT_RECONNECT_TIMEOUT, check_reconnect_timeout
from ..sidecar import find_server_binary
from ..state import F64Array, SessionState
from ..transports.base import BatchProbe, BatchReport, BatchTransport, Transport

_T = TypeVar("_T")

SIDECAR_DIR_ENV = "ESA_RLLIB_SIDECAR_DIR"
"""Overrides the default node sidecar directory (``$TMPDIR/esa-rllib-<uid>``)."""

_KEEPER = Path(__file__).with_name("_keeper.py")
_TAIL = 2000


def default_sidecar_dir() -> Path:
    """``$ESA_RLLIB_SIDECAR_DIR``, else ``<tempdir>/esa-rllib-<uid>``."""
    explicit = os.environ.get(SIDECAR_DIR_ENV)
    if explicit:
        return Path(explicit)
    return Path(tempfile.gettempdir()) / f"esa-rllib-{os.getuid()}"


def _private_dir(path: Path) -> Path:
    """Creates ``path`` (mode 0700) if needed and checks that only this user can use it."""
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    info = os.lstat(path)
    if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid() or info.st_mode & 0o077:
        raise EsaError(
            f"expected {path} to be a directory of this user that no one else can use "
            f"(mode 0700), got mode {stat.filemode(info.st_mode)} owned by uid {info.st_uid}"
        )
    return path


def _tail(path: Path) -> str:
    try:
        return path.read_text(errors="replace")[-_TAIL:].strip() or "(empty)"
    except OSError:
        return "(none)"


def _lock(fd: int, kind: int, deadline: float, what: str) -> None:
    while True:
        try:
            fcntl.flock(fd, kind | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if time.monotonic() > deadline:
                raise ServerUnavailable(
                    f"timed out waiting for {what}", StatusCode.UNAVAILABLE
                ) from None
            time.sleep(0.01)


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie, exited but not yet reaped, does not)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    with contextlib.suppress(OSError, IndexError):
        # Linux: the state follows the parenthesized command name.
        stat_line = Path(f"/proc/{pid}/stat").read_text()
        return stat_line[stat_line.rindex(")") + 2] != "Z"
    return True


class NodeSidecar:
    """This process's hold on its node's shared esa-server; starts it if none runs.

    Args:
        directory: The node's sidecar directory (default :func:`default_sidecar_dir`);
            created with mode 0700 if missing.
        binary: The esa-server executable, found as :func:`esa_client.sidecar.find_server_binary`
            does if None. Used only when this runner starts the sidecar.
        server_args: Extra esa-server arguments (e.g. ``("--session-ttl", "3600")``), used
            only when this runner starts the sidecar: the first runner's win.
        startup_timeout: Seconds to wait for the start lock and for a new server.

    Attributes:
        address: The sidecar's gRPC address, ``unix:DIR/esa-PID.sock``.
        directory: The sidecar directory.
        started: True if this call started the sidecar (False: it joined a running one).

    Raises:
        EsaError: If the directory is not private to this user, or the binary is missing.
        ServerUnavailable: If the server does not start in time (with its output).
    """

    def __init__(
        self,
        directory: str | os.PathLike[str] | None = None,
        *,
        binary: str | os.PathLike[str] | None = None,
        server_args: Sequence[str] = (),
        startup_timeout: float = 60.0,
    ) -> None:
        """Joins (or starts) the node's sidecar."""
        self.directory = _private_dir(Path(directory) if directory else default_sidecar_dir())
        self.started = False
        deadline = time.monotonic() + startup_timeout
        self._users: int | None = os.open(
            self.directory / "users.lock", os.O_RDWR | os.O_CREAT, 0o600
        )
        try:
            start = os.open(self.directory / "start.lock", os.O_RDWR | os.O_CREAT, 0o600)
            try:
                _lock(start, fcntl.LOCK_EX, deadline, f"{self.directory}/start.lock")
                # Held until this process exits (or release()): the keeper stops the server
                # only when no process holds it.
                _lock(self._users, fcntl.LOCK_SH, deadline, f"{self.directory}/users.lock")
                address = self._running(deadline)
                if address is None:
                    address = self._start(binary, server_args, deadline)
                    self.started = True
                self.address = address
            finally:
                os.close(start)  # also lets start.lock go
        except BaseException:
            self.release()
            raise

    def _running(self, deadline: float) -> str | None:
        """The recorded server's address if it runs; else clears the record."""
        info_path = self.directory / "server.json"
        try:
            info = json.loads(info_path.read_text())
        except (OSError, ValueError):
            return None
        address = str(info.get("address", ""))
        keeper, server = int(info.get("keeper_pid", 0)), int(info.get("server_pid", 0))
        socket = Path(address[len("unix:") :]) if address.startswith("unix:") else None
        if _alive(keeper) and _alive(server) and socket is not None and socket.exists():
            return address
        # The server died: its keeper notices within a poll and exits; wait for that.
        while _alive(keeper) and time.monotonic() < deadline:
            time.sleep(0.05)
        # (A keeper killed with SIGKILL leaves its record; the server followed it.)
        with contextlib.suppress(FileNotFoundError):
            info_path.unlink()
        return None

    def _start(
        self, binary: str | os.PathLike[str] | None, server_args: Sequence[str], deadline: float
    ) -> str:
        executable = str(find_server_binary(binary))
        info_path, failed = self.directory / "server.json", self.directory / "server.failed"
        with contextlib.suppress(FileNotFoundError):
            failed.unlink()
        with open(self.directory / "keeper.log", "ab") as log:
            # The keeper forks into the background and this first process exits at once.
            subprocess.run(
                [sys.executable, str(_KEEPER), str(self.directory), executable, *server_args],
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                # Its own session: signals to this runner's process group miss it.
                start_new_session=True,
                close_fds=True,
                check=True,
                timeout=max(1.0, deadline - time.monotonic()),
            )
        # We hold start.lock: the record that appears is our keeper's.
        while True:
            with contextlib.suppress(OSError, ValueError, KeyError):
                return str(json.loads(info_path.read_text())["address"])
            if failed.exists() or time.monotonic() > deadline:
                what = "did not start" if failed.exists() else "did not start in time"
                raise ServerUnavailable(
                    f"the node sidecar in {self.directory} {what}; keeper log:\n"
                    f"{_tail(self.directory / 'keeper.log')}\nserver log:\n"
                    f"{_tail(self.directory / 'server.log')}",
                    StatusCode.UNAVAILABLE,
                )
            time.sleep(0.01)

    def serving(self) -> bool:
        """True while the server this runner joined still runs (its record names it)."""
        try:
            info = json.loads((self.directory / "server.json").read_text())
        except (OSError, ValueError):
            return False
        return (
            info.get("address") == self.address
            and _alive(int(info.get("keeper_pid", 0)))
            and _alive(int(info.get("server_pid", 0)))
        )

    def release(self) -> None:
        """Stops using the sidecar (it stops once no process on the node uses it)."""
        if self._users is not None:
            os.close(self._users)
            self._users = None

    def __del__(self) -> None:
        """Releases the hold."""
        with contextlib.suppress(Exception):
            self.release()


class SidecarTransport:
    """A :class:`~esa_client.transports.base.Transport` to the node's sidecar that follows it.

    A sidecar that dies (killed, out of memory) is replaced: after a call fails with
    ``ServerUnavailable`` and the sidecar's record no longer names a live server, this
    runner joins the node's sidecar again (:class:`NodeSidecar` starts a new one, or
    finds the one another runner started) and connects to its new socket; the failed
    call's error is then raised, and the batch's reconnect loop repeats the step against
    the new server, recreating the sessions it lacks (``SessionNotFound``).

    Args:
        join: Joins the node's sidecar (a new :class:`NodeSidecar`).
        connect: A client of the sidecar at an address.
    """

    def __init__(
        self,
        join: Callable[[], NodeSidecar],
        connect: Callable[[str], EsaClient],
    ) -> None:
        """Joins the sidecar and connects."""
        self._join, self._connect = join, connect
        self.sidecar = join()
        try:
            self.client = connect(self.sidecar.address)
        except BaseException:
            self.sidecar.release()
            raise
        self.generation = 0
        """How many times this runner followed a replaced sidecar."""
        self.on_follow: Callable[[str], None] | None = None
        """Told the new sidecar's address whenever this runner follows one."""

    def _call(self, call: Callable[[Transport], _T]) -> _T:
        try:
            return call(self.client.transport)
        except ServerUnavailable:
            self.follow()
            raise

    def follow(self) -> bool:
        """Joins a new sidecar if the one in use is gone; True if it did."""
        if self.sidecar.serving():
            return False
        sidecar = self._join()
        try:
            client = self._connect(sidecar.address)
        except BaseException:
            sidecar.release()
            raise
        old_client, old_sidecar = self.client, self.sidecar
        self.client, self.sidecar = client, sidecar
        self.generation += 1
        with contextlib.suppress(EsaError):
            old_client.close()
        old_sidecar.release()
        if self.on_follow is not None:
            self.on_follow(sidecar.address)
        return True

    def create_session(self, session_id: str, config: esa_pb2.SessionConfig) -> str:
        """``CreateSession`` on the current sidecar."""
        return self._call(lambda t: t.create_session(session_id, config))

    def get_session(self, session_id: str) -> SessionState:
        """``GetSession`` on the current sidecar."""
        return self._call(lambda t: t.get_session(session_id))

    def close_session(self, session_id: str) -> None:
        """``CloseSession`` on the current sidecar."""
        self._call(lambda t: t.close_session(session_id))

    def end_episode(self, session_id: str) -> int:
        """``EndEpisode`` on the current sidecar."""
        return self._call(lambda t: t.end_episode(session_id))

    def probe(
        self,
        session_id: str,
        step: int,
        action: F64Array,
        episode_start: bool,
        action_scale: F64Array | None,
    ) -> tuple[F64Array, F64Array]:
        """``Probe`` on the current sidecar."""
        return self._call(lambda t: t.probe(session_id, step, action, episode_start, action_scale))

    def report(
        self, session_id: str, step: int, q_value: float, q_reference: float | None
    ) -> F64Array:
        """``Report`` on the current sidecar."""
        return self._call(lambda t: t.report(session_id, step, q_value, q_reference))

    def open_batch(
        self, ids: Sequence[str], action_dim: int, *, use_stream: bool
    ) -> BatchTransport:
        """A batch that reopens itself on the current sidecar's transport."""
        return _SidecarBatch(self, ids, action_dim, use_stream)

    def healthy(self, timeout: float, *, wait_for_ready: bool = False) -> bool:
        """True if the current sidecar answers as serving."""
        return self.client.healthy(timeout=timeout, wait_for_ready=wait_for_ready)

    def close(self) -> None:
        """Closes the client and lets go of the sidecar."""
        self.client.close()
        self.sidecar.release()


class _SidecarBatch(BatchTransport):
    """A batch over :class:`SidecarTransport`: reopened on the sidecar that replaced one."""

    def __init__(
        self, owner: SidecarTransport, ids: Sequence[str], action_dim: int, use_stream: bool
    ) -> None:
        self._owner = owner
        self._open = (tuple(ids), action_dim, use_stream)
        self._generation = owner.generation
        self._batch = owner.client.transport.open_batch(ids, action_dim, use_stream=use_stream)

    def _current(self) -> BatchTransport:
        if self._generation != self._owner.generation:
            with contextlib.suppress(EsaError):
                self._batch.close()
            ids, action_dim, use_stream = self._open
            transport = self._owner.client.transport
            self._batch = transport.open_batch(ids, action_dim, use_stream=use_stream)
            self._generation = self._owner.generation
        return self._batch

    def probe(self, request: BatchProbe) -> tuple[F64Array, F64Array]:
        """``ProbeBatch``."""
        return self._owner._call(lambda _: self._current().probe(request))

    def report(self, request: BatchReport) -> F64Array:
        """``ReportBatch``."""
        return self._owner._call(lambda _: self._current().report(request))

    def report_then_probe(
        self, report: BatchReport, probe: BatchProbe
    ) -> tuple[F64Array, F64Array]:
        """The report, then the probe, as the current sidecar's batch sends them."""
        return self._owner._call(lambda _: self._current().report_then_probe(report, probe))

    def close(self) -> None:
        """Closes the batch's stream, if any."""
        self._batch.close()


@dataclass(frozen=True)
class EsaService:
    """Where the EnvRunners' sessions live (the ``service`` of :func:`~esa_client.rllib.with_esa`).

    With no address and no Zenoh locator, each EnvRunner uses its node's sidecar
    (:class:`NodeSidecar`): one ``esa-server`` per node, started on first use.

    Args:
        address: A running server over gRPC, ``host:port`` or ``unix:/path``, reachable
            from every node that runs env runners.
        zenoh: Zenoh endpoint(s) of a server started with ``--zenoh`` (or of a router
            reaching it), e.g. ``"tcp/10.0.0.5:7447"``.
        shards: With ``zenoh``: N servers started with ``--shard i/N``; each session lives
            on the shard its id hashes to.
        zenoh_prefix: The servers' ``--zenoh-prefix`` (None: the client's default).
        token_file: A file holding the servers' auth token (a path valid on every node);
            None falls back to ``$ESA_AUTH_TOKEN`` in the runner's environment.
        timeout: Deadline of every call, in seconds.
        sidecar_dir: The node sidecar's directory (None: ``$ESA_RLLIB_SIDECAR_DIR``, else
            ``<tempdir>/esa-rllib-<uid>``).
        sidecar_args: Extra ``esa-server`` arguments for the node sidecar, e.g.
            ``("--session-ttl", "3600")`` (the first runner of a node starts it).
        startup_timeout: Seconds to wait for the node sidecar (or a server) to be ready.
        reconnect_timeout: Seconds a runner's batch keeps retrying a lost server (a node
            sidecar that died is restarted, or the one another runner restarted joined)
            before ``on_unavailable`` applies.
        on_unavailable: ``"raise"`` (default): the runner's step raises
            ``ServerUnavailable`` after one more reconnection, and the runner fails as for
            any error of its env; ``"skip"``: its envs execute the sampled actions without
            ESA until an episode of one of them starts, where the server is tried again
            (counted as ``env_runners/esa/unavailable_steps``).
    """

    address: str | None = None
    zenoh: str | Sequence[str] | None = None
    shards: int | None = None
    zenoh_prefix: str | None = None
    token_file: str | None = None
    timeout: float = 5.0
    sidecar_dir: str | None = None
    sidecar_args: tuple[str, ...] = field(default_factory=tuple)
    startup_timeout: float = 60.0
    reconnect_timeout: float = DEFAULT_RECONNECT_TIMEOUT
    on_unavailable: OnUnavailable = "raise"

    def __post_init__(self) -> None:
        """Checks that the fields describe one kind of service."""
        if self.address is not None and self.zenoh is not None:
            raise ValueError(
                f"expected address or zenoh, got both ({self.address!r}, {self.zenoh!r})"
            )
        if self.shards is not None and (self.zenoh is None or self.shards < 1):
            raise ValueError(f"expected shards >= 1 together with zenoh, got {self.shards!r}")
        if not self.timeout > 0 or not self.startup_timeout > 0:
            raise ValueError(
                f"expected timeout and startup_timeout > 0, got {self.timeout}, "
                f"{self.startup_timeout}"
            )
        check_reconnect_timeout(self.reconnect_timeout)
        check_on_unavailable(self.on_unavailable)
        object.__setattr__(self, "sidecar_args", tuple(str(a) for a in self.sidecar_args))
        if self.zenoh is not None and not isinstance(self.zenoh, str):
            object.__setattr__(self, "zenoh", tuple(self.zenoh))

    @property
    def uses_sidecar(self) -> bool:
        """True when the runners use their node's sidecar."""
        return self.address is None and self.zenoh is None

    def connect(self) -> EsaClient:
        """Connects this process; closing the client also lets go of the node sidecar.

        Raises:
            EsaError: If the server cannot be reached (or the sidecar not started) within
                ``startup_timeout``.
        """
        if self.zenoh is not None:
            return EsaClient.connect(
                self.zenoh,
                transport="zenoh",
                shards=self.shards,
                prefix=self.zenoh_prefix,
                timeout=self.timeout,
                token_file=self.token_file,
                reconnect_timeout=self.reconnect_timeout,
            )
        if self.address is None:
            return self._connect_sidecar()
        client = EsaClient.connect(
            self.address,
            timeout=self.timeout,
            token_file=self.token_file,
            reconnect_timeout=self.reconnect_timeout,
        )
        try:
            client.wait_ready(self.startup_timeout)
        except BaseException:
            client.close()
            raise
        return client

    def _connect_sidecar(self) -> EsaClient:
        """A client of the node's sidecar that follows it when it is replaced."""

        def join() -> NodeSidecar:
            return NodeSidecar(
                self.sidecar_dir,
                server_args=self.sidecar_args,
                startup_timeout=self.startup_timeout,
            )

        def connect(address: str) -> EsaClient:
            # The sidecar is this user's own, on a private socket: it has no token.
            client = EsaClient.connect(address, timeout=self.timeout, token_file=None)
            try:
                client.wait_ready(self.startup_timeout)
            except BaseException:
                client.close()
                raise
            return client

        transport = SidecarTransport(join, connect)
        client = EsaClient(transport, address=transport.sidecar.address, timeout=self.timeout)
        transport.on_follow = lambda address: setattr(client, "address", address)
        client.reconnect_timeout = self.reconnect_timeout
        return client

"""The project's Prefect server: one local ``prefect server start`` per storage root, started
by the first command that needs it and reused by the next ones.

Prefect's embedded (ephemeral) server started again for every command: 15-46 s of
start-up per command on this project's loaded 2-core machines, and timeouts ended commands
in tracebacks.  A server that keeps running costs that once.

* **Where.**  Its state lives in ``$PREFECT_HOME`` when set, else ``<storage>/.prefect``
  (the job's storage root): the SQLite database ``prefect.db``, the server's log
  ``plantdyn-server.log`` and the state file ``plantdyn-server.json`` (pid, port, API URL,
  Prefect version, start time; written atomically).
* **Reuse.**  A recorded server is reused when its pid is still a ``prefect server start``
  process on the recorded port (``/proc/<pid>/cmdline``: a reused pid is never mistaken
  for it, nor signalled) and ``GET /api/health`` answers.  A dead pid, a foreign process
  or another Prefect version: the state file is stale and replaced.
* **Concurrency.**  Start-ups hold an exclusive lock (``plantdyn-server.lock``,
  ``fcntl.flock``: released by the kernel when a process dies); a second command waits for
  it and then reuses the first one's server.
* **Readiness.**  The wait for ``/api/health`` tolerates a loaded machine
  (:data:`START_TIMEOUT_S`, or ``$PLANTDYN_PREFECT_START_TIMEOUT_S``), saying every
  :data:`TICK_S` seconds that it is still waiting.  A server that exits or does not answer
  in time is stopped and reported as :class:`PrefectStartError` (exit 2) with its log's
  last lines and the fixes.
* **Lifetime.**  The server runs in its own session: it outlives the command (that is the
  point) and a Ctrl-C in the terminal does not reach it.  ``plantdyn server stop`` stops it.

``PREFECT_API_URL`` set by the user (environment or active Prefect profile) wins: no
project server is started.
"""

from __future__ import annotations

import contextlib
import http.client
import json
import os
import re
import signal
import socket
import stat
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from urllib.parse import urlsplit

from pipeline.errors import UserInputError

__all__ = [
    "HOST",
    "START_TIMEOUT_ENV",
    "START_TIMEOUT_S",
    "STATE_FILE",
    "PrefectStartError",
    "ServerState",
    "ServerStatus",
    "configured_api_url",
    "ensure_server",
    "healthy",
    "project_prefect",
    "read_state",
    "server_home",
    "server_status",
    "stop_server",
]

STATE_FILE = "plantdyn-server.json"
LOCK_FILE = "plantdyn-server.lock"
LOG_FILE = "plantdyn-server.log"
HOST = "127.0.0.1"
"""Loopback only: the server has no authentication."""
START_TIMEOUT_ENV = "PLANTDYN_PREFECT_START_TIMEOUT_S"
#: Longest wait for a starting server's ``/api/health``, s.  A first start migrates a new
#: database: 10-40 s on 2 loaded cores; the embedded server's 20 s ended commands.
START_TIMEOUT_S = 300.0
#: How long a stopping server may take before it is killed, s.
STOP_TIMEOUT_S = 20.0
#: Seconds between "still waiting" lines.
TICK_S = 10.0
_FREE_PORT_ATTEMPTS = 3


class PrefectStartError(UserInputError):
    """Prefect's server could not be started or reached (CLI exit code 2, like bad input:
    the user can go on -- the message says how)."""


_FIXES = ("run the command again with --no-prefect (the same work without Prefect), or "
          "set PREFECT_API_URL to a running Prefect server's /api address")


def _note(message: str) -> None:
    print(f"plantdyn: {message}", file=sys.stderr, flush=True)


@dataclass(frozen=True)
class ServerState:
    """What the state file records about a started server.

    Attributes
    ----------
    pid : int
        Process id of ``prefect server start`` (also its process group: own session).
    port : int
        Its TCP port on :data:`HOST`.
    api_url : str
        ``http://127.0.0.1:<port>/api``.
    prefect_home : str
        Its ``PREFECT_HOME`` (database, log, this state file).
    prefect_version : str
        Prefect's version that started it (another version is not reused).
    started_utc : str
        ISO 8601 start time.
    """

    pid: int
    port: int
    api_url: str
    prefect_home: str
    prefect_version: str
    started_utc: str


@dataclass(frozen=True)
class ServerStatus:
    """The project server of one ``PREFECT_HOME`` as :func:`server_status` found it.

    Attributes
    ----------
    home : Path
        The ``PREFECT_HOME`` looked at.
    state : ServerState or None
        The state file's content (``None``: no readable state file).
    running : bool
        ``state.pid`` is a ``prefect server start`` process on ``state.port``.
    healthy : bool
        ``GET <api_url>/health`` answered.
    """

    home: Path
    state: ServerState | None
    running: bool
    healthy: bool

    def describe(self) -> str:
        """One line: ``running …``, ``starting …``, ``stale …`` or ``stopped …``."""
        st = self.state
        if st is None:
            return f"stopped: no project Prefect server recorded in {self.home}"
        if self.running and self.healthy:
            return (f"running: {st.api_url} (pid {st.pid}, Prefect {st.prefect_version}, "
                    f"since {st.started_utc}; dashboard {st.api_url.removesuffix('/api')}; "
                    f"PREFECT_HOME={st.prefect_home})")
        if self.running:
            return (f"starting or not answering: pid {st.pid} on port {st.port} does not "
                    f"answer GET {st.api_url}/health (log: {self.home / LOG_FILE})")
        return (f"stale: the state file names pid {st.pid}, which is not a Prefect server on "
                f"port {st.port}; the next command replaces it")


# ------------------------------------------------------------------------ helpers
def server_home(storage_root: str | os.PathLike) -> Path:
    """The project server's ``PREFECT_HOME``: ``$PREFECT_HOME`` if set, else
    ``<storage_root>/.prefect`` (absolute).

    Parameters
    ----------
    storage_root : path
        The results root (a job's ``storage:``).
    """
    env = os.environ.get("PREFECT_HOME")
    home = Path(env).expanduser() if env else Path(storage_root) / ".prefect"
    return home.resolve()


def _regular_or_missing(path: Path) -> bool:
    try:
        return stat.S_ISREG(os.lstat(path).st_mode)
    except FileNotFoundError:
        return True


def _prefect_version() -> str:
    from importlib.metadata import version

    return version("prefect")


def _timeout_s() -> float:
    raw = os.environ.get(START_TIMEOUT_ENV)
    if not raw:
        return START_TIMEOUT_S
    try:
        value = float(raw)
    except ValueError:
        value = -1.0
    if not value >= 0:
        raise PrefectStartError(f"{START_TIMEOUT_ENV}={raw!r} is not a number of seconds >= 0; "
                                f"unset it (default {START_TIMEOUT_S:g} s) or give e.g. 600")
    return value


def read_state(home: Path) -> ServerState | None:
    """The state file in ``home``, or ``None`` when missing, not a regular file or not
    readable as one (a stale or damaged file is replaced by the next start).

    Parameters
    ----------
    home : Path
        The server's ``PREFECT_HOME``.
    """
    path = Path(home) / STATE_FILE
    try:
        if not stat.S_ISREG(os.lstat(path).st_mode):  # never open a FIFO or a device
            return None
        raw = json.loads(path.read_text(encoding="utf-8"))
        return ServerState(**{k: raw[k] for k in ServerState.__dataclass_fields__})
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _write_state(home: Path, state: ServerState) -> None:
    from pipeline.adapters.safe_write import write_atomically

    write_atomically(home / STATE_FILE, json.dumps(asdict(state), indent=1).encode(),
                     option="the Prefect server's state file")


def _remove_state(home: Path) -> None:
    path = home / STATE_FILE
    if path.exists() and _regular_or_missing(path):  # only our regular file
        path.unlink(missing_ok=True)


def _is_our_server(state: ServerState) -> bool:
    """``state.pid`` is a live ``prefect server start`` on ``state.port`` (a zombie or a
    reused pid is not)."""
    try:
        args = Path(f"/proc/{state.pid}/cmdline").read_bytes().decode(errors="replace")
    except OSError:
        return False
    parts = args.split("\0")
    return "prefect" in parts and "server" in parts and "start" in parts and \
        str(state.port) in parts


def healthy(api_url: str, timeout_s: float = 3.0) -> bool:
    """``GET <api_url>/health`` answers 200 (no proxy: the server is local).

    Parameters
    ----------
    api_url : str
        A Prefect API URL ending in ``/api``.
    timeout_s : float
        Longest wait for the answer, s.
    """
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
    try:
        with opener.open(f"{api_url.rstrip('/')}/health", timeout=timeout_s) as resp:
            return resp.status == 200
    except (OSError, ValueError, http.client.HTTPException):
        return False


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((HOST, 0))
        return int(s.getsockname()[1])


def _tail(path: Path) -> str:
    """The server log's cause, on one line: its last exception line (``…Error: …``) and
    its last line."""
    try:
        with open(path, "rb") as fh:
            fh.seek(max(0, os.fstat(fh.fileno()).st_size - 50_000))
            lines = [ln.strip() for ln in fh.read().decode(errors="replace").splitlines()]
    except OSError:
        return "(no log)"
    lines = [ln for ln in lines if ln]
    causes = [ln for ln in lines if re.match(r"^[\w.]*(Error|Exception)\b.*:", ln)]
    text = " | ".join(dict.fromkeys(causes[-1:] + lines[-1:]))
    return text[-600:] or "(empty)"


def _gone(pid: int, proc: subprocess.Popen | None) -> bool:
    if proc is not None:
        return proc.poll() is not None
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False
    state = Path(f"/proc/{pid}/stat")
    with contextlib.suppress(OSError):
        return state.read_text().rsplit(")", 1)[1].split()[0] == "Z"
    return False


def _terminate(pid: int, proc: subprocess.Popen | None = None) -> None:
    """SIGTERM the server's process group (its own session), SIGKILL after
    :data:`STOP_TIMEOUT_S`.  Only called for a process known to be ours."""
    def send(sig: int) -> None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            if os.getpgid(pid) == pid:
                os.killpg(pid, sig)
            else:
                os.kill(pid, sig)

    send(signal.SIGTERM)
    deadline = time.monotonic() + STOP_TIMEOUT_S
    while not _gone(pid, proc) and time.monotonic() < deadline:
        time.sleep(0.2)
    if not _gone(pid, proc):
        send(signal.SIGKILL)
        if proc is not None:
            proc.wait()


@contextlib.contextmanager
def _locked(home: Path, note: Callable[[str], None]) -> Iterator[None]:
    """Hold ``home/plantdyn-server.lock`` exclusively (waiting, with a note, for another
    command that holds it)."""
    import fcntl

    path = home / LOCK_FILE
    if not _regular_or_missing(path):
        raise PrefectStartError(f"{path} is not a regular file; remove it or set PREFECT_HOME "
                                "to another folder")
    try:
        fh = open(path, "a+")  # noqa: SIM115 - closed below, which releases the lock
    except OSError as exc:
        raise PrefectStartError(f"cannot open the Prefect server's lock file {path} "
                                f"({exc.strerror or exc}); {_FIXES}") from None
    with fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            note(f"another command is starting the Prefect server in {home}; waiting for it")
            fcntl.flock(fh, fcntl.LOCK_EX)
        yield  # closing the file releases the lock


def _wait_healthy(state: ServerState, timeout_s: float, note: Callable[[str], None],
                  proc: subprocess.Popen | None = None) -> bool:
    """Poll ``/api/health`` until it answers (True), or the process is gone or
    ``timeout_s`` passed (False); a line every :data:`TICK_S` seconds."""
    t0 = time.monotonic()
    next_tick = t0 + TICK_S
    while True:
        if healthy(state.api_url):
            return True
        if (proc.poll() is not None) if proc is not None else not _is_our_server(state):
            return False
        now = time.monotonic()
        if now - t0 >= timeout_s:
            return False
        if now >= next_tick:
            note(f"[{now - t0:5.0f} s] still waiting for the Prefect server at "
                 f"{state.api_url} (a first start creates its database; a busy machine is "
                 f"slower; gives up after {timeout_s:g} s)")
            next_tick += TICK_S
        time.sleep(0.5)


# ------------------------------------------------------------------------ the API
def server_status(home: Path) -> ServerStatus:
    """What runs in ``home`` (no lock taken, nothing changed).

    Parameters
    ----------
    home : Path
        The server's ``PREFECT_HOME`` (:func:`server_home`).
    """
    home = Path(home)
    state = read_state(home)
    running = state is not None and _is_our_server(state)
    return ServerStatus(home, state, running, running and healthy(state.api_url))


def ensure_server(home: Path, *, timeout_s: float | None = None,
                  note: Callable[[str], None] = _note) -> ServerState:
    """The running project server of ``home``: the recorded one if it answers, else a new
    one (started under the lock; a stale state file is replaced).

    Parameters
    ----------
    home : Path
        The server's ``PREFECT_HOME`` (:func:`server_home`); created if missing.
    timeout_s : float, optional
        Longest wait for ``/api/health``, s (default ``$PLANTDYN_PREFECT_START_TIMEOUT_S``
        or :data:`START_TIMEOUT_S`).
    note : callable (str)
        Told what happens (default: a line on stderr).

    Returns
    -------
    ServerState
        The server, answering ``GET /api/health``.

    Raises
    ------
    PrefectStartError
        The server exited, did not answer within ``timeout_s``, or ``home`` cannot be
        created; the message has the log's last lines and the fixes.
    """
    home = Path(home)
    timeout_s = _timeout_s() if timeout_s is None else timeout_s
    try:
        home.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PrefectStartError(f"cannot create the Prefect server's folder {home} "
                                f"({exc.strerror or exc}); {_FIXES}") from None
    with _locked(home, note):
        state = read_state(home)
        if state is not None:
            if _is_our_server(state) and state.prefect_version == _prefect_version():
                if healthy(state.api_url) or _wait_healthy(state, timeout_s, note):
                    note(f"reusing the Prefect server at {state.api_url} (pid {state.pid})")
                    return state
                note(f"the Prefect server pid {state.pid} does not answer; restarting it")
                _terminate(state.pid)
            elif _is_our_server(state):
                note(f"stopping the Prefect {state.prefect_version} server (pid {state.pid}): "
                     f"this is Prefect {_prefect_version()}")
                _terminate(state.pid)
            else:
                note(f"replacing a stale Prefect server record (pid {state.pid} is not "
                     "running a Prefect server)")
            _remove_state(home)
        return _start(home, timeout_s, note)


def _start(home: Path, timeout_s: float, note: Callable[[str], None]) -> ServerState:
    """Start ``prefect server start`` on a free port and wait until it answers."""
    log = home / LOG_FILE
    if not _regular_or_missing(log):
        raise PrefectStartError(f"{log} is not a regular file; remove it or set PREFECT_HOME "
                                "to another folder")
    env = {**os.environ, "PREFECT_HOME": str(home), "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
           "DO_NOT_TRACK": "1"}
    env.pop("PREFECT_API_URL", None)  # the server must not talk to another server
    for _attempt in range(_FREE_PORT_ATTEMPTS):  # a free port can be taken before binding
        port = _free_port()
        t0 = time.monotonic()
        note(f"starting the project's Prefect server on {HOST}:{port} (PREFECT_HOME={home}); "
             "it keeps running for the next commands (plantdyn server stop)")
        try:
            out = open(log, "wb")  # noqa: SIM115 - closed below (the server has its copy)
        except OSError as exc:
            raise PrefectStartError(f"cannot write the Prefect server's log {log} "
                                    f"({exc.strerror or exc}); {_FIXES}") from None
        with out:
            # own session: outlives this command; a Ctrl-C in the terminal does not reach it
            proc = subprocess.Popen(
                [sys.executable, "-m", "prefect", "server", "start", "--host", HOST,
                 "--port", str(port)], env=env, cwd=home, stdin=subprocess.DEVNULL,
                stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        state = ServerState(proc.pid, port, f"http://{HOST}:{port}/api", str(home),
                            _prefect_version(),
                            datetime.now(UTC).isoformat(timespec="seconds"))
        try:
            _write_state(home, state)
            ok = _wait_healthy(state, timeout_s, note, proc)
        except BaseException:  # Ctrl-C or a failed write: leave no half-started server
            _terminate(proc.pid, proc)
            _remove_state(home)
            raise
        if ok:
            note(f"Prefect server ready at {state.api_url} (pid {proc.pid}) after "
                 f"{time.monotonic() - t0:.1f} s")
            return state
        code = proc.poll()
        _terminate(proc.pid, proc)
        _remove_state(home)
        tail = _tail(log)
        if code is not None and "address already in use" in tail.lower():
            continue
        what = (f"exited with code {code}" if code is not None else
                f"did not answer GET {state.api_url}/health within {timeout_s:g} s")
        longer = "" if code is not None else f", or allow a longer start: {START_TIMEOUT_ENV}=600"
        raise PrefectStartError(
            f"the project's Prefect server (PREFECT_HOME={home}) {what}; its log {log} says: "
            f"{tail}; {_FIXES}{longer}")
    raise PrefectStartError(f"no free port on {HOST} for the Prefect server after "
                            f"{_FREE_PORT_ATTEMPTS} attempts; {_FIXES}")


def stop_server(home: Path, *, note: Callable[[str], None] = _note) -> str:
    """Stop the project server of ``home`` and remove its state file; a stale state file
    is removed without signalling anything.

    Parameters
    ----------
    home : Path
        The server's ``PREFECT_HOME`` (:func:`server_home`).
    note : callable (str)
        Told when the lock is held by a starting command.

    Returns
    -------
    str
        What was done, in words.
    """
    home = Path(home)
    if not home.is_dir():
        return f"no project Prefect server recorded in {home}"
    with _locked(home, note):
        state = read_state(home)
        if state is None:
            return f"no project Prefect server recorded in {home}"
        if not _is_our_server(state):
            _remove_state(home)
            return (f"removed a stale state file (pid {state.pid} is not a Prefect server); "
                    "nothing was running")
        _terminate(state.pid)
        _remove_state(home)
        return f"stopped the Prefect server at {state.api_url} (pid {state.pid})"


def configured_api_url() -> str | None:
    """``PREFECT_API_URL`` from the environment or the active Prefect profile (or a test
    harness's settings), else ``None``."""
    if os.environ.get("PREFECT_API_URL"):
        return os.environ["PREFECT_API_URL"]
    from prefect.settings import get_current_settings

    url = get_current_settings().api.url
    return str(url) if url else None


def _check_configured(url: str) -> None:
    """A loopback ``PREFECT_API_URL`` that does not answer is a message, not a traceback
    later (a remote or cloud URL is left to Prefect: it may need credentials)."""
    if urlsplit(url).hostname in ("127.0.0.1", "localhost", "::1") and not healthy(url):
        raise PrefectStartError(
            f"PREFECT_API_URL={url} does not answer GET {url.rstrip('/')}/health; start that "
            "server, unset PREFECT_API_URL (plantdyn then starts its own), or run the command "
            "again with --no-prefect")


@contextlib.contextmanager
def project_prefect(storage_root: str | os.PathLike, *, home: Path | None = None,
                    note: Callable[[str], None] = _note) -> Iterator[str]:
    """Prefect's API for a command on ``storage_root``: the user's ``PREFECT_API_URL`` if
    set, else the project server (:func:`ensure_server`), set as ``PREFECT_API_URL`` in
    this process (environment and Prefect settings) for the duration of the block.

    Parameters
    ----------
    storage_root : path
        The results root whose server is used (unless ``PREFECT_HOME`` is set).
    home : Path, optional
        The server's ``PREFECT_HOME`` instead of :func:`server_home` ``(storage_root)``.
    note : callable (str)
        Told what happens (default: a line on stderr).

    Yields
    ------
    str
        The API URL.

    Raises
    ------
    PrefectStartError
        The server cannot be started or the configured one does not answer.
    """
    from flows.common import prefect_env_defaults

    prefect_env_defaults()
    configured = configured_api_url()
    if configured:
        _check_configured(configured)
        yield configured
        return
    state = ensure_server(home if home is not None else server_home(storage_root),
                          note=note)
    from prefect.settings import PREFECT_API_URL, temporary_settings

    previous = os.environ.get("PREFECT_API_URL")
    os.environ["PREFECT_API_URL"] = state.api_url  # also for subprocesses (serve's runs)
    try:
        with temporary_settings(updates={PREFECT_API_URL: state.api_url}):
            yield state.api_url
    finally:
        if previous is None:
            os.environ.pop("PREFECT_API_URL", None)
        else:
            os.environ["PREFECT_API_URL"] = previous

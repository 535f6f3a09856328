"""``geocoder cluster up|down``: a real Dask cluster on this machine, as on a cluster's nodes.

``up`` starts one ``dask scheduler`` and N ``dask worker`` processes (each under a nanny,
one thread, the worker preload of ``workers/``), optionally with TLS between all of them
(certificates made by :mod:`geocoder.certs`), waits for the workers and writes
``cluster.json`` (address, dashboard, process ids, certificate directory) into its
directory. Pass that file, or the address, to ``--scheduler``. ``down`` shuts the
cluster down and removes the file. The processes outlive the command that started them.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from .errors import GeocoderError
from .runtime import WORKER_ENV

CLUSTER_FILE = "cluster.json"


def default_directory() -> str:
    """The directory ``cluster up`` and ``cluster down`` use when given none.

    Returns
    -------
    str
        ``$GEOCODER_CLUSTER_DIR`` if set and not empty, else ``~/.geocoder/cluster``.
    """
    return os.environ.get("GEOCODER_CLUSTER_DIR") or os.path.join(os.path.expanduser("~"), ".geocoder", "cluster")


def preload_script() -> str | None:
    """The worker preload of the source tree (``workers/geocoder_preload.py``), if present.

    Returns
    -------
    str or None
        Its absolute path, or None when the package is not run from a source tree that has it.
    """
    p = Path(__file__).resolve().parents[1] / "workers" / "geocoder_preload.py"
    return str(p) if p.exists() else None


@dataclass
class ClusterInfo:
    """What ``cluster up`` wrote to ``cluster.json``.

    Attributes
    ----------
    address : str
        The scheduler's address (``tcp://...`` or ``tls://...``).
    dashboard : str
        The link to the scheduler's dashboard.
    directory : str
        The cluster's directory (``cluster.json``, logs, certificates).
    scheduler_pid : int
        Process id of the scheduler.
    worker_pids : list of int
        Process ids of the ``dask worker`` commands (each a worker's nanny), one per worker.
    tls : str or None
        Directory of the TLS certificates, or None for a cluster without TLS.
    started : float
        When the cluster was started (seconds since the epoch).
    """

    address: str
    dashboard: str
    directory: str
    scheduler_pid: int
    worker_pids: list[int] = field(default_factory=list)
    tls: str | None = None
    started: float = 0.0

    @property
    def file(self) -> str:
        """The path of ``cluster.json`` in :attr:`directory`."""
        return os.path.join(self.directory, CLUSTER_FILE)

    def lines(self) -> list[str]:
        """What ``geocoder cluster up`` prints: the address, the dashboard, how to use and stop it.

        Returns
        -------
        list of str
            One line each, without newlines.
        """
        return [
            f"scheduler {self.address} with {len(self.worker_pids)} worker(s){' (TLS)' if self.tls else ''}",
            f"dashboard {self.dashboard}"
            + (" (plain HTTP, not covered by TLS: anyone who reaches this port sees the cluster)" if self.tls else ""),
            f"use it: geocoder register ... --scheduler {self.file}",
            *([] if self.tls else [f"     or: export DASK_SCHEDULER_ADDRESS={self.address}"]),
            f"stop it: geocoder cluster down{'' if self.directory == default_directory() else ' --dir ' + self.directory}",
        ]


def _dask_command() -> list[str]:
    exe = shutil.which("dask", path=str(Path(sys.executable).parent))
    return [exe] if exe else [sys.executable, "-m", "dask"]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def read_info(directory: str | None = None) -> ClusterInfo | None:
    """The description of the cluster started from ``directory`` (its ``cluster.json``).

    Parameters
    ----------
    directory : str, optional
        The cluster's directory (default :func:`default_directory`).

    Returns
    -------
    ClusterInfo or None
        As ``cluster up`` wrote it, or None when there is no ``cluster.json``. Whether its
        processes still run is not checked.

    Raises
    ------
    GeocoderError
        If ``cluster.json`` exists but is not a cluster file.
    """
    path = os.path.join(directory or default_directory(), CLUSTER_FILE)
    try:
        with open(path) as f:
            return ClusterInfo(**json.load(f))
    except FileNotFoundError:
        return None
    except (ValueError, TypeError) as exc:
        raise GeocoderError(f"{path}: not a cluster file ({exc})") from exc


def up(workers: int = 2, *, directory: str | None = None, tls: bool = False, memory_limit: str = "auto",
       host: str = "127.0.0.1", port: int = 0, dashboard_port: int = 0, timeout: float = 120.0) -> ClusterInfo:
    """Start a scheduler and ``workers`` worker processes; return their description.

    Parameters
    ----------
    workers : int
        Number of worker processes (one thread each).
    directory : str, optional
        Where ``cluster.json``, the logs and the certificates go (default :func:`default_directory`).
    tls : bool
        Encrypt and authenticate every connection with certificates made here.
    memory_limit : str
        Per-worker memory limit (Dask syntax).
    host, port, dashboard_port : str, int, int
        Where the scheduler listens (0 = a free port).
    timeout : float
        Seconds to wait for the scheduler and all workers.

    Returns
    -------
    ClusterInfo
        The running cluster, as written to ``cluster.json`` in ``directory``.

    Raises
    ------
    GeocoderError
        If a cluster started from ``directory`` is still running, or a process exited or
        did not start within ``timeout`` (everything started is stopped again).
    """
    directory = os.path.abspath(directory or default_directory())
    old = read_info(directory)
    if old is not None and _alive(old.scheduler_pid):
        raise GeocoderError(f"a cluster is already running from {old.file} ({old.address}); run 'geocoder cluster down' first")
    os.makedirs(directory, exist_ok=True)
    sched_file = os.path.join(directory, "scheduler.json")
    if os.path.exists(sched_file):
        os.unlink(sched_file)
    env = dict(os.environ, **WORKER_ENV)
    dask_yaml = Path(__file__).resolve().parents[1] / "workers" / "dask.yaml"
    if dask_yaml.exists():
        env.setdefault("DASK_CONFIG", str(dask_yaml))
    cmd = _dask_command()
    tls_dir = None
    proto_args: list[str] = []
    if tls:
        from .certs import make_certificates, role_args

        tls_dir = os.path.join(directory, "tls")
        make_certificates(tls_dir, names=("localhost", "127.0.0.1", host))
        proto_args = ["--protocol", "tls"]
    procs: list[subprocess.Popen] = []

    def spawn(args: list[str], log_name: str) -> subprocess.Popen:
        log = open(os.path.join(directory, log_name), "w")
        p = subprocess.Popen(args, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        log.close()
        procs.append(p)
        return p

    try:
        sched = spawn(
            [*cmd, "scheduler", "--host", host, "--port", str(port), "--dashboard-address", f"{host}:{dashboard_port}",
             "--scheduler-file", sched_file, *proto_args, *(role_args(tls_dir, "scheduler") if tls else [])],
            "scheduler.log",
        )
        _wait(lambda: os.path.exists(sched_file), timeout, "the scheduler to start", directory, sched)
        preload = preload_script()
        from ._version import __version__

        worker_args = [
            "--scheduler-file", sched_file, "--nthreads", "1", "--memory-limit", memory_limit,
            "--local-directory", os.path.join(directory, "worker-space"),
            *(role_args(tls_dir, "worker") if tls else []),
        ]
        # the preload's own options are the words after it, so it comes last
        preload_args = ["--preload", preload, f"--geocoder-version={__version__}"] if preload else []
        for i in range(workers):
            spawn([*cmd, "worker", *worker_args, "--name", f"geocoder-worker-{i}", *preload_args], f"worker-{i}.log")
        with open(sched_file) as f:
            address = json.load(f)["address"]
        info = ClusterInfo(address=address, dashboard="", directory=directory, scheduler_pid=sched.pid,
                           worker_pids=[p.pid for p in procs[1:]], tls=tls_dir, started=time.time())
        from distributed import Client

        from .certs import client_security

        with Client(address, security=client_security(tls_dir) if tls else None, timeout=timeout) as c:
            deadline = time.time() + timeout
            while len(c.scheduler_info(n_workers=-1)["workers"]) < workers:
                for p in procs:
                    if p.poll() is not None:
                        raise GeocoderError(f"a cluster process exited with code {p.returncode}; see the logs in {directory}")
                if time.time() > deadline:
                    raise GeocoderError(f"only {len(c.scheduler_info(n_workers=-1)['workers'])} of {workers} workers started "
                                        f"within {timeout:.0f} s; see the logs in {directory}")
                time.sleep(0.2)
            info.dashboard = c.dashboard_link
        tmp = info.file + ".tmp"
        with open(tmp, "w") as f:
            json.dump(asdict(info), f, indent=1)
        os.replace(tmp, info.file)
        return info
    except BaseException:
        for p in procs:
            _terminate(p.pid)
        raise


def _wait(ready, timeout: float, what: str, directory: str, proc: subprocess.Popen) -> None:
    deadline = time.time() + timeout
    while not ready():
        if proc.poll() is not None:
            raise GeocoderError(f"{what} failed (exit code {proc.returncode}); see the logs in {directory}")
        if time.time() > deadline:
            raise GeocoderError(f"timed out waiting for {what}; see the logs in {directory}")
        time.sleep(0.1)


def _terminate(pid: int, grace: float = 10.0) -> bool:
    """SIGTERM the process group of ``pid``, SIGKILL it after ``grace`` seconds.

    Returns whether the process was still running.
    """
    running = _alive(pid)
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(pid, sig)
        except (ProcessLookupError, PermissionError):
            return running
        deadline = time.time() + grace
        while time.time() < deadline:
            try:
                if os.waitpid(pid, os.WNOHANG)[0] == pid:
                    return running
            except ChildProcessError:
                if not _alive(pid):
                    return running
            time.sleep(0.1)
    return running


@dataclass
class Stopped:
    """What :func:`down` found running and stopped.

    Attributes
    ----------
    info : ClusterInfo
        The cluster as ``cluster.json`` described it.
    scheduler_running : bool
        Whether the scheduler was still running (and was stopped).
    workers_running : int
        How many worker processes were still running (and were stopped).
    """

    info: ClusterInfo
    scheduler_running: bool
    workers_running: int

    def line(self) -> str:
        """What ``geocoder cluster down`` prints.

        Returns
        -------
        str
            One line: what was stopped and what had already stopped.
        """
        dead = len(self.info.worker_pids) - self.workers_running
        parts = [f"stopped {self.info.address}" if self.scheduler_running else f"the scheduler {self.info.address} had already stopped",
                 f"{self.workers_running} worker process(es) stopped"]
        if dead:
            parts.append(f"{dead} had already stopped")
        return "; ".join(parts)


def down(directory: str | None = None) -> Stopped | None:
    """Stop the cluster described in ``directory`` and remove its ``cluster.json``.

    Each process group gets SIGTERM, then SIGKILL if it is still running 10 s later.

    Parameters
    ----------
    directory : str, optional
        The cluster's directory (default :func:`default_directory`).

    Returns
    -------
    Stopped or None
        What was still running and was stopped; None when there is no ``cluster.json``.

    Raises
    ------
    GeocoderError
        If ``cluster.json`` exists but is not a cluster file.
    """
    info = read_info(directory)
    if info is None:
        return None
    workers = sum(_terminate(pid) for pid in info.worker_pids)
    scheduler = _terminate(info.scheduler_pid)
    os.unlink(info.file)
    return Stopped(info, scheduler, workers)

"""A real PostgreSQL server for the tests, on loopback, in a folder of its own.

Debian's PostgreSQL (``apt-get install -y postgresql``) is installed when it is missing
and the tests run as root (`ensure_debian_package`, which installs HAProxy for the
failover test too); elsewhere the tests that need it skip, saying why. The server is
initialised with trust authentication for loopback, started on a free port, and each
test gets a database of its own (`PostgresServer.new_database`). Start and stop take
about a second each.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import socket
import subprocess
import tempfile
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TypeVar

import psycopg
import pytest

T = TypeVar("T")

#: Where Debian puts each major version's server programs.
_DEBIAN_BIN = Path("/usr/lib/postgresql")
_INSTALL_LOCK = Path(tempfile.gettempdir()) / "focustrack-apt-install.lock"


def server_bin() -> Path | None:
    """The folder of the newest PostgreSQL's initdb and pg_ctl, or None."""
    found = sorted(_DEBIAN_BIN.glob("*/bin/initdb"), key=lambda p: int(p.parent.parent.name))
    return found[-1].parent if found else None


def ensure_debian_package(package: str, found: Callable[[], T | None]) -> T:
    """`found()`, once Debian's `package` is installed with apt-get if `found()` says it is
    missing (one pytest worker at a time, under a file lock); skip if impossible."""
    with _INSTALL_LOCK.open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if (present := found()) is not None:
            return present
        if os.geteuid() != 0 or shutil.which("apt-get") is None:
            pytest.skip(f"{package}: not installed, and no root with apt-get to install it")
        env = os.environ | {"DEBIAN_FRONTEND": "noninteractive"}
        install = ["apt-get", "install", "-y", package]
        if subprocess.run(install, capture_output=True, env=env).returncode != 0:
            subprocess.run(["apt-get", "update"], capture_output=True, env=env)
            done = subprocess.run(install, capture_output=True, text=True, env=env)
            if done.returncode != 0:
                pytest.skip(f"{package}: apt-get could not install it: {done.stderr[-500:]}")
        if (present := found()) is None:
            pytest.skip(f"{package}: installed, but not where it was looked for")
        return present


def ensure_postgresql() -> Path:
    """The server programs' folder, installed with apt-get if missing; skip if impossible."""
    return ensure_debian_package("postgresql", server_bin)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class PostgresServer:
    """One PostgreSQL server on 127.0.0.1:`port` with its data in `folder` (trust auth)."""

    def __init__(self, bin_dir: Path, folder: Path) -> None:
        self.bin_dir, self.folder, self.port = bin_dir, folder, free_port()
        self.data = folder / "data"
        # initdb and the server refuse to run as root: as the postgres user then
        self._as = ["su", "postgres", "-s", "/bin/sh", "-c"] if os.geteuid() == 0 else None
        if self._as is not None:
            shutil.chown(folder, "postgres")
        self._run("initdb", "-D", str(self.data), "-A", "trust", "-U", "postgres")

    def _run(self, program: str, *args: str) -> None:
        command = [str(self.bin_dir / program), *args]
        if self._as is not None:
            command = [*self._as, " ".join(f"'{part}'" for part in command)]
        done = subprocess.run(command, capture_output=True, text=True, timeout=60)
        if done.returncode != 0:
            raise RuntimeError(f"{program} failed: {done.stdout}\n{done.stderr}")

    def start(self) -> None:
        options = f"-p {self.port} -k {self.folder} -h 127.0.0.1 -c fsync=off"
        log = str(self.folder / "server.log")
        self._run("pg_ctl", "-D", str(self.data), "-o", options, "-l", log, "-w", "start")

    def stop(self, mode: str = "fast") -> None:
        """Stop the server (`mode`: smart, fast, immediate: immediate is a crash)."""
        self._run("pg_ctl", "-D", str(self.data), "-m", mode, "-w", "stop")

    def url(self, database: str = "postgres") -> str:
        return f"postgresql://postgres@127.0.0.1:{self.port}/{database}"

    def new_database(self, encoding: str | None = None) -> str:
        """A new, empty database's URL (in `encoding`, e.g. SQL_ASCII: the server's default
        otherwise)."""
        name = f"test_{uuid.uuid4().hex[:12]}"
        options = "" if encoding is None else f" ENCODING '{encoding}' TEMPLATE template0"
        with psycopg.connect(self.url(), autocommit=True) as admin:
            admin.execute(f'CREATE DATABASE "{name}"{options}')
        return self.url(name)


@contextmanager
def postgres_server() -> Iterator[PostgresServer]:
    """A started server, stopped and removed afterwards."""
    bin_dir = ensure_postgresql()
    with tempfile.TemporaryDirectory(prefix="focustrack-pg-") as folder:
        server = PostgresServer(bin_dir, Path(folder))
        server.start()
        try:
            yield server
        finally:
            server.stop("immediate")

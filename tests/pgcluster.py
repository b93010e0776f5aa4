"""A real PostgreSQL 15 cluster for tests: ``initdb`` and ``pg_ctl`` in a temporary folder.

One cluster per test session (:func:`start_cluster`); each test gets its own database
(:meth:`Cluster.new_database`). The server listens on a free TCP port on 127.0.0.1 and on a
unix socket in its own folder; it trusts local connections except for the role
:data:`PASSWORD_ROLE`, which must give :data:`PASSWORD` (the password tests). initdb refuses
to run as root, so when the tests run as root the binaries run as the ``postgres`` user
(``runuser -u postgres --``) in a folder that user owns. No shared memory of the host's
cluster and no system service is touched.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import pwd
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from procs import free_port

BIN = Path("/usr/lib/postgresql/15/bin")
SUPERUSER = "postgres"
PASSWORD_ROLE = "wardmap_pw"
PASSWORD = "s3cret-for-tests"
_NAMES = itertools.count(1)


def missing() -> str | None:
    """Why no cluster can be started here (None: it can)."""
    if not (BIN / "initdb").is_file() or not (BIN / "pg_ctl").is_file():
        return f"PostgreSQL 15 server binaries not found in {BIN} (Debian: apt-get install postgresql-15)"
    if os.geteuid() == 0:
        try:
            pwd.getpwnam(SUPERUSER)
        except KeyError:
            return "running as root and there is no 'postgres' user to run initdb as"
        if shutil.which("runuser") is None:
            return "running as root and runuser is missing"
    return None


@dataclass
class Cluster:
    """A running cluster.

    Attributes:
        folder: owns the data directory (``data``), the socket folder and the log.
        port: its TCP port on 127.0.0.1.
        postgis: whether the PostGIS extension can be created in its databases.
    """

    folder: Path
    port: int
    postgis: bool = False

    @property
    def data(self) -> Path:
        return self.folder / "data"

    @property
    def log(self) -> Path:
        return self.folder / "server.log"

    def url(self, database: str, user: str = SUPERUSER) -> str:
        """The store URL of ``database`` over TCP (no password in it)."""
        return f"postgresql://{user}@127.0.0.1:{self.port}/{database}"

    def psql(self, sql: str, database: str = "postgres") -> str:
        """Run ``sql`` with psql as the superuser; its output (stdout). Fails the test on error."""
        done = subprocess.run(
            [str(BIN / "psql"),
             "-h", "127.0.0.1", "-p", str(self.port), "-U", SUPERUSER, "-d", database,
             "-v", "ON_ERROR_STOP=1", "-At", "-c", sql],
            capture_output=True, text=True, timeout=60, env={**os.environ, "PGPASSWORD": ""},
        )
        if done.returncode != 0:
            raise RuntimeError(f"psql {sql!r}: {done.stderr.strip()}")
        return done.stdout

    def new_database(self, template: str = "template1") -> str:
        """Create a database (a copy of ``template``: by default an empty one); its name."""
        name = f"wardmap_test_{os.getpid()}_{next(_NAMES)}"
        self.psql(f"CREATE DATABASE {name} TEMPLATE {template}")
        return name

    def pg_ctl(self, *args: str, timeout: float = 60.0) -> None:
        """Run ``pg_ctl -D DATA ARGS`` (as the ``postgres`` user when root)."""
        _run([str(BIN / "pg_ctl"), "-D", str(self.data), "-l", str(self.log), "-w", *args], timeout)

    def stop(self, mode: str = "fast") -> None:
        """Stop the server: ``fast`` (clients disconnected, a shutdown checkpoint) or ``immediate``
        (no checkpoint: for a cluster about to be deleted)."""
        self.pg_ctl("stop", "-m", mode)

    def start(self) -> None:
        self.pg_ctl("start", "-o", f"-p {self.port} -c listen_addresses=127.0.0.1 "
                                  f"-c unix_socket_directories={self.folder}")


def _as_owner() -> list[str]:
    return ["runuser", "-u", SUPERUSER, "--"] if os.geteuid() == 0 else []


def _run(cmd: list[str], timeout: float) -> None:
    done = subprocess.run([*_as_owner(), *cmd], capture_output=True, text=True, timeout=timeout)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[:2])}: {done.stdout.strip()} {done.stderr.strip()}")


@contextmanager
def start_cluster() -> Iterator[Cluster]:
    """initdb a new cluster in a temporary folder, start it, yield it, stop it and remove it."""
    folder = Path(tempfile.mkdtemp(prefix="wardmap-pg-"))
    try:
        if os.geteuid() == 0:
            shutil.chown(folder, SUPERUSER, SUPERUSER)
        cluster = Cluster(folder, free_port())
        _run([str(BIN / "initdb"), "-D", str(cluster.data), "-U", SUPERUSER, "-A", "trust",
              "--no-sync", "-E", "UTF8", "--locale=C"], 120)
        # The password role must authenticate; everyone else is trusted (first match wins).
        hba = cluster.data / "pg_hba.conf"
        rules = (f"host all {PASSWORD_ROLE} 127.0.0.1/32 scram-sha-256\n"
                 "local all all trust\nhost all all 127.0.0.1/32 trust\n")
        _run(["sh", "-c", f"printf '%s' '{rules}' > {hba}"], 10)
        # fsync off: a test cluster need not survive power loss (commits are still acknowledged
        # only after the server has them; the store's durability rule is PostgreSQL's own).
        conf = cluster.data / "postgresql.conf"
        _run(["sh", "-c", f"printf 'fsync = off\\nmax_connections = 200\\n' >> {conf}"], 10)
        cluster.start()
        try:
            cluster.psql(f"CREATE ROLE {PASSWORD_ROLE} LOGIN SUPERUSER PASSWORD '{PASSWORD}'")
            cluster.postgis = cluster.psql(
                "SELECT count(*) FROM pg_available_extensions WHERE name = 'postgis'").strip() == "1"
            yield cluster
        finally:
            with contextlib.suppress(RuntimeError):  # already stopped by a test
                cluster.stop("immediate")
    finally:
        shutil.rmtree(folder, ignore_errors=True)

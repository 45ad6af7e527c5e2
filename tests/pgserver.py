"""A throwaway PostgreSQL server for the tests: initdb into a temporary folder, started on a Unix socket there
(no TCP port), trust authentication, fsync off; stopped at the end. Run as the `postgres` user where the
tests run as root (the server refuses root). Debian's postgresql package provides it (`.ci/run` installs it
and sets MLAQC_REQUIRE_POSTGRES=1, so that a server that cannot start fails the tests there instead of
skipping them)."""

from __future__ import annotations

import glob
import os
import shutil
import subprocess
import tempfile
import uuid
from pathlib import Path

REQUIRED = os.environ.get("MLAQC_REQUIRE_POSTGRES") == "1"
PORT = 54329
USER = "mlaqc"


def _binary(name: str) -> str | None:
    found = shutil.which(name)
    if found:
        return found
    candidates = sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}"))
    return candidates[-1] if candidates else None


class Server:
    """A running server; `url(db)` for a database in it, `new_database()` a fresh one."""

    def __init__(self) -> None:
        self.root = Path(tempfile.mkdtemp(prefix="mlaqc-pg-"))
        self.data, self.sock = self.root / "data", self.root / "sock"
        self.sock.mkdir()
        self.as_user: list[str] = []
        if os.geteuid() == 0:
            shutil.chown(self.root, "postgres")
            shutil.chown(self.sock, "postgres")
            runuser = shutil.which("runuser")
            self.as_user = [runuser, "-u", "postgres", "--"] if runuser else ["su", "postgres", "-c"]
        initdb, pg_ctl = _binary("initdb"), _binary("pg_ctl")
        if not (initdb and pg_ctl):
            raise RuntimeError("no PostgreSQL server programs (initdb, pg_ctl) on this machine")
        self.pg_ctl = pg_ctl
        self._run([initdb, "-D", str(self.data), "-A", "trust", "-U", USER, "--no-sync", "-E", "UTF8"])
        opts = f"-k {self.sock} -c listen_addresses='' -p {PORT} -c fsync=off -c max_connections=40"
        self._run([pg_ctl, "-D", str(self.data), "-o", opts, "-l", str(self.root / "log"), "-w", "start"])

    def _run(self, cmd: list[str]) -> None:
        if self.as_user and self.as_user[0] == "su":
            cmd = [*self.as_user, " ".join(cmd)]
        else:
            cmd = [*self.as_user, *cmd]
        subprocess.run(cmd, check=True, capture_output=True, cwd=self.root)

    def url(self, database: str = "postgres") -> str:
        return f"postgresql://{USER}@/{database}?host={self.sock}&port={PORT}"

    def new_database(self) -> str:
        """A fresh, empty database; its URL."""
        import psycopg

        name = f"t_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(self.url(), autocommit=True) as conn:
            conn.execute(f"CREATE DATABASE {name}")
        return self.url(name)

    def stop(self) -> None:
        try:
            self._run([self.pg_ctl, "-D", str(self.data), "-m", "immediate", "stop"])
        finally:
            shutil.rmtree(self.root, ignore_errors=True)


def start() -> tuple[Server | None, str]:
    """(a running server, "") or (None, why not)."""
    try:
        import psycopg  # noqa: F401
    except ImportError:
        return None, "psycopg is not installed"
    try:
        return Server(), ""
    except (RuntimeError, OSError, subprocess.CalledProcessError, KeyError) as exc:
        detail = getattr(exc, "stderr", b"") or b""
        return None, f"cannot start a PostgreSQL server: {exc} {detail.decode(errors='replace')[-300:]}"

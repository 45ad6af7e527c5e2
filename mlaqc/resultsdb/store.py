"""Opening the results database (SQLite file or PostgreSQL server) and recording inspections into it.

Every failure is one sentence (`DatabaseError`, exit status 4): a locked, full, read-only or unreachable
database, a file that is no results database, a schema newer than this mlaqc knows. An inspection that
cannot be recorded still writes its report folder (the caller goes on; see mlaqc.commands.inspect).
"""

from __future__ import annotations

import contextlib
import os
import sqlite3
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from mlaqc.errors import MlaqcError
from mlaqc.resultsdb.record import DEFECT_COLUMNS, Identity, run_key
from mlaqc.resultsdb.schema import SCHEMA_VERSION, statements

BUSY_TIMEOUT_S = 30.0  # a writer waits this long for another station's transaction before giving up
CONNECT_TIMEOUT_S = 5  # PostgreSQL: an unreachable server is said after this long


class DatabaseError(MlaqcError):
    """The results database could not be opened, read or written (exit status 4)."""

    exit_status = 4


def default_target() -> str:
    """$MLAQC_DB, else results.sqlite in the user's data folder ($XDG_DATA_HOME/mlaqc, ~/.local/share/mlaqc)."""
    if os.environ.get("MLAQC_DB"):
        return os.environ["MLAQC_DB"]
    base = os.environ.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local", "share")
    return os.path.join(base, "mlaqc", "results.sqlite")


def _is_url(target: str) -> bool:
    return target.startswith(("postgresql://", "postgres://"))


def _where(target: str) -> str:
    """The database as a sentence names it (a URL without its password)."""
    if not _is_url(target):
        return target
    head, _, rest = target.partition("://")
    creds, at, host = rest.rpartition("@")
    return f"{head}://{creds.split(':')[0]}@{host}" if at else target


class ResultsDB:
    """An open results database: `record` one inspection, `query` rows for the lot views."""

    def __init__(self, conn: Any, dialect: str, where: str) -> None:
        self.conn, self.dialect, self.where = conn, dialect, where

    def _sql(self, sql: str) -> str:
        return sql if self.dialect == "sqlite" else sql.replace("?", "%s")

    def close(self) -> None:
        self.conn.close()

    def __enter__(self) -> ResultsDB:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------------------------ writing

    def record(self, record: dict, identity: Identity, report_dir: str | None = None) -> int:
        """Record one inspection (`record_from_report`'s dict) in one transaction; the same inspection
        recorded again (a batch run again: same raw, config, identity and folder) replaces its record.
        Returns its id."""
        key = run_key(record, identity, report_dir)
        fields = {**record["fields"], "run_key": key, "recorded_utc": _now(), "lot": identity.lot,
                  "wafer": identity.wafer, "array_id": identity.array, "position": identity.position,
                  "station": identity.station, "operator": identity.operator,
                  "report_dir": os.path.abspath(report_dir) if report_dir else None,
                  "config_hash": record["config_hash"]}
        cols = ", ".join(fields)
        marks = ", ".join("?" for _ in fields)
        with self._transaction() as cur:
            if record["config_hash"]:
                cur.execute(self._sql("INSERT INTO configs (hash, body) VALUES (?, ?) ON CONFLICT (hash) DO NOTHING"),
                            (record["config_hash"], record["config_text"]))
            cur.execute(self._sql("DELETE FROM flagged_lenses WHERE inspection_id IN "
                                  "(SELECT id FROM inspections WHERE run_key = ?)"), (key,))
            cur.execute(self._sql("DELETE FROM inspections WHERE run_key = ?"), (key,))
            cur.execute(self._sql(f"INSERT INTO inspections ({cols}) VALUES ({marks}) RETURNING id"),
                        tuple(fields.values()))
            (ident,) = cur.fetchone()
            if record["defects"]:
                cur.executemany(self._sql(f"INSERT INTO flagged_lenses (inspection_id, {', '.join(DEFECT_COLUMNS)}) "
                                          f"VALUES (?, {', '.join('?' for _ in DEFECT_COLUMNS)})"),
                                [(ident, *row) for row in record["defects"]])
        return int(ident)

    # ------------------------------------------------------------------------------------ reading

    def query(self, sql: str, params: tuple = ()) -> list[tuple]:
        try:
            cur = self.conn.cursor()
            cur.execute(self._sql(sql), params)
            rows = cur.fetchall()
            if self.dialect == "postgresql":
                self.conn.rollback()  # reads only: end the implicit transaction
            return rows
        except Exception as exc:  # noqa: BLE001 - every driver error becomes one sentence
            raise _sentence(exc, self.where, "read") from exc

    @contextlib.contextmanager
    def _transaction(self):
        """One write transaction: BEGIN IMMEDIATE on SQLite (the write lock up front, waiting for another
        writer up to BUSY_TIMEOUT_S), committed on success, rolled back on any error or interruption."""
        try:
            cur = self.conn.cursor()
            if self.dialect == "sqlite":
                cur.execute("BEGIN IMMEDIATE")
        except Exception as exc:  # noqa: BLE001
            raise _sentence(exc, self.where, "write") from exc
        try:
            yield cur
            self.conn.commit()
        except BaseException as exc:
            _rollback(self.conn)
            if isinstance(exc, DatabaseError) or not isinstance(exc, Exception):
                raise
            raise _sentence(exc, self.where, "write") from exc

    # ------------------------------------------------------------------------------------ schema

    def schema_version(self) -> int | None:
        """The database's schema version; None for an empty database; DatabaseError for one that is not
        a results database."""
        try:
            version = self.schema_version_in(self.conn.cursor())
            if self.dialect == "postgresql":
                self.conn.rollback()
            return version
        except DatabaseError:
            raise
        except Exception as exc:  # noqa: BLE001
            raise _sentence(exc, self.where, "read") from exc

    def migrate(self) -> None:
        """Bring the schema up to SCHEMA_VERSION, each version in one transaction (none written by a
        newer mlaqc is touched)."""
        while True:
            with self._transaction() as cur:
                if self.dialect == "postgresql":  # one migrator at a time across stations
                    cur.execute("SELECT pg_advisory_xact_lock(7120113)")
                version = self.schema_version_in(cur)
                if version is not None and version > SCHEMA_VERSION:
                    raise _newer(self.where, version, "write to")
                if version == SCHEMA_VERSION:
                    return
                for statement in statements((version or 0) + 1, self.dialect):
                    cur.execute(statement)

    def schema_version_in(self, cur) -> int | None:
        """schema_version within an open transaction (cursor `cur`)."""
        if self.dialect == "sqlite":
            cur.execute("SELECT name FROM sqlite_master WHERE type = 'table'")
        else:
            cur.execute("SELECT table_name FROM information_schema.tables WHERE table_schema = current_schema()")
        tables = {r[0] for r in cur.fetchall()}
        if "schema_info" not in tables:
            if tables - {"sqlite_sequence"}:
                raise DatabaseError(f"{self.where} is a database, but not an mlaqc results database "
                                    f"(it has tables {', '.join(sorted(tables)[:5])} and no schema_info)")
            return None
        cur.execute("SELECT MAX(version) FROM schema_info")
        row = cur.fetchone()
        return int(row[0]) if row and row[0] is not None else None


def _rollback(conn) -> None:
    try:
        conn.rollback()
    except Exception:  # noqa: BLE001 - the connection is gone: nothing was committed
        pass


def _newer(where: str, version: int, doing: str) -> DatabaseError:
    return DatabaseError(f"the results database {where} has schema version {version}, newer than this mlaqc "
                         f"knows ({SCHEMA_VERSION}): update mlaqc to {doing} it")


def _first_line(exc: Exception) -> str:
    """An exception's message as one line (its type's name when it has none)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


def _sentence(exc: Exception, where: str, doing: str) -> DatabaseError:
    """A driver's error as one sentence a bench operator can act on."""
    if isinstance(exc, DatabaseError):
        return exc
    text = _first_line(exc)
    low = text.lower()
    if "locked" in low or "busy" in low:
        why = f"it stayed locked by another writer for {BUSY_TIMEOUT_S:.0f} s"
    elif "readonly" in low or "read-only" in low or "permission denied" in low:
        why = "it is read-only here"
    elif "full" in low or "no space" in low:
        why = "the disk (or the database) is full"
    elif "not a database" in low or "malformed" in low:
        why = "the file is not an SQLite database (or is damaged)"
    else:
        why = text.rstrip(".")
    return DatabaseError(f"cannot {doing} the results database {where}: {why}")


def open_database(target: str | None = None, *, create: bool = True) -> ResultsDB:
    """Open (and with `create`, make or migrate) the results database at `target`: a file path (SQLite) or
    a postgresql:// URL; default `default_target()`. DatabaseError (one sentence) if it cannot be used."""
    target = target or default_target()
    if _is_url(target):
        db = _open_postgresql(target)
    else:
        db = _open_sqlite(target, create)
    try:
        if create:
            db.migrate()
        else:
            version = db.schema_version()
            if version is None:
                raise DatabaseError(f"the results database {db.where} is empty: nothing has been recorded in it")
            if version > SCHEMA_VERSION:
                raise _newer(db.where, version, "read")
    except BaseException:
        db.close()
        raise
    return db


def _open_sqlite(path: str, create: bool) -> ResultsDB:
    p = Path(path).expanduser()
    if p.is_dir():
        raise DatabaseError(f"cannot open the results database {path}: it is a folder, not a file")
    if not p.exists():
        if not create:
            raise DatabaseError(f"there is no results database at {path} (inspections record into it; "
                                "--db names another)")
        if path == default_target():
            try:
                p.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise DatabaseError(f"cannot create the results database's folder {p.parent}: "
                                    f"{(exc.strerror or str(exc)).rstrip('.')}") from exc
        elif not p.parent.is_dir():
            raise DatabaseError(f"cannot create the results database {path}: folder {p.parent} does not exist")
    try:
        # autocommit mode: every transaction is begun explicitly (BEGIN IMMEDIATE)
        conn = sqlite3.connect(str(p), timeout=BUSY_TIMEOUT_S, isolation_level=None)
        conn.execute("PRAGMA foreign_keys = ON")
        if create:
            _wal(conn)
    except sqlite3.Error as exc:
        raise _sentence(exc, path, "open") from exc
    return ResultsDB(conn, "sqlite", path)


def _wal(conn: sqlite3.Connection) -> None:
    """Write-ahead logging: readers never block the writer (lot queries while stations record). Kept off
    where it cannot be switched on (a file system without shared memory, another connection mid-change):
    the default rollback journal is as safe, only slower to read beside a writer."""
    try:
        conn.execute("PRAGMA journal_mode = WAL").fetchall()
    except sqlite3.OperationalError as exc:
        if "readonly" in str(exc).lower() or "read-only" in str(exc).lower():
            raise


def _open_postgresql(url: str) -> ResultsDB:
    try:
        import psycopg
    except ImportError as exc:
        raise DatabaseError("a postgresql:// results database needs the psycopg package "
                            "(python3 -m pip install 'psycopg[binary]')") from exc
    where = _where(url)
    try:
        conn = psycopg.connect(url, connect_timeout=CONNECT_TIMEOUT_S)
    except Exception as exc:  # noqa: BLE001
        raise DatabaseError(f"cannot reach the results database {where}: {_first_line(exc)}") from exc
    return ResultsDB(conn, "postgresql", where)

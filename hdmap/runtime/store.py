"""SQLite under a service's data dir: WAL, explicit transactions, a small meta table.

Durability: WAL with ``synchronous=NORMAL`` (the default here) survives a process
crash (SIGKILL) with every committed transaction; ``synchronous=FULL`` also
survives power loss at some cost per commit (``--sync full``).

Corruption is a fault of its own (:class:`DatabaseCorrupt`): no retry repairs it, an
operator has to restore or remove the file. ``connect(..., check=True)`` looks for it when
a service opens its database (:func:`check_integrity`), and :func:`transaction` raises it
when SQLite meets it later.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Protocol

import numpy as np


class StorageError(RuntimeError):
    """The data dir cannot keep what we would acknowledge (disk full, read-only, corrupt).

    ``transient`` is False when SQLite refused the statement itself (a constraint, a bad
    query: a bug of the caller) rather than the storage: retrying the same work later
    fails the same way, so a stage sets such work aside instead of replaying it forever.
    """

    def __init__(self, message: str, transient: bool = True):
        super().__init__(message)
        self.transient = transient


class StateLost(StorageError):
    """A participant could not reload its state from the database after a rollback (an I/O
    error): the process's memory no longer matches its file. Nothing is lost on disk; the
    service ends with :data:`EXIT_RESTART` so that a restart reloads everything."""


EXIT_RESTART = 75
"""Exit code of a service that must be restarted to reload its state (sysexits
``EX_TEMPFAIL``): ``hdmap up`` restarts it."""


class DatabaseCorrupt(StorageError):
    """The database file is damaged (SQLITE_CORRUPT, SQLITE_NOTADB, a failed integrity
    check): permanent until an operator restores or removes the file.

    It is a :class:`StorageError` (``transient`` True: never the work's fault, so a stage
    keeps its input for later instead of setting it aside), whose ``path`` is the file and
    ``cause`` SQLite's words; ``str()`` is one line naming both.
    """

    def __init__(self, path: str | Path, cause: str):
        cause = " ".join(cause.split())  # quick_check reports on several lines
        super().__init__(f"{path}: database is corrupt ({cause})", transient=True)
        self.path = str(path)
        self.cause = cause


EXIT_CORRUPT = 65
"""Exit code of a service that stopped on a :class:`DatabaseCorrupt` (``EX_DATAERR`` of
sysexits.h): a permanent fault; ``hdmap up`` does not restart such a service."""

_CORRUPT_CODES = frozenset({sqlite3.SQLITE_CORRUPT, sqlite3.SQLITE_NOTADB})

_STORAGE_CODES = frozenset(
    {
        sqlite3.SQLITE_PERM,
        sqlite3.SQLITE_BUSY,
        sqlite3.SQLITE_LOCKED,
        sqlite3.SQLITE_NOMEM,
        sqlite3.SQLITE_READONLY,
        sqlite3.SQLITE_IOERR,
        sqlite3.SQLITE_CORRUPT,
        sqlite3.SQLITE_FULL,
        sqlite3.SQLITE_CANTOPEN,
        sqlite3.SQLITE_PROTOCOL,
        sqlite3.SQLITE_NOTADB,
    }
)


def is_storage_failure(exc: sqlite3.Error) -> bool:
    """Whether SQLite failed because of the storage (full, read-only, I/O, corrupt,
    locked) rather than because of the statement."""
    code = getattr(exc, "sqlite_errorcode", None)
    return code is not None and (code & 0xFF) in _STORAGE_CODES


def is_corruption(exc: sqlite3.Error) -> bool:
    """Whether SQLite failed because the file is damaged (malformed image, not a database)."""
    code = getattr(exc, "sqlite_errorcode", None)
    return code is not None and (code & 0xFF) in _CORRUPT_CODES


def db_file(conn: sqlite3.Connection) -> str:
    """The file of ``conn``'s main database ('?' if SQLite cannot say; ':memory:' for none)."""
    try:
        for _seq, name, file in conn.execute("PRAGMA database_list"):
            if name == "main":
                return str(file) or ":memory:"
    except sqlite3.Error:
        pass
    return "?"


def check_integrity(conn: sqlite3.Connection, path: str | Path) -> None:
    """Raise :class:`DatabaseCorrupt` naming ``path`` unless ``PRAGMA quick_check(1)`` says ok.

    Why quick_check: it reads every page once and checks each b-tree page's structure, the
    free list and that every page is used exactly once, which catches damaged or
    overwritten pages anywhere in the file, without ``integrity_check``'s cross-check of
    index contents against their tables (about 2.5 times as slow). Measured on a 100 MB
    database shaped like ingest's (dedup table and log): 0.12 s with the file in the page
    cache, 1 s on the first read after writing, i.e. one sequential read of the file,
    small next to a service's start (Zenoh session, catch-up); a data dir of tens of GB
    would make it minutes. ``(1)`` stops at the first problem: it costs the same on a
    good file and reports one line on a bad one. Other SQLite errors (locked, I/O) are
    raised as they are.
    """
    try:
        rows = conn.execute("PRAGMA quick_check(1)").fetchall()
    except sqlite3.Error as exc:
        if is_corruption(exc):
            raise DatabaseCorrupt(path, str(exc)) from exc
        raise  # locked, I/O error...: a storage failure, not damage
    if [tuple(r) for r in rows] != [("ok",)]:
        found = "; ".join(str(r[0]).replace("*** in database main ***", "").strip() for r in rows)
        raise DatabaseCorrupt(path, f"quick_check: {found}")


def connect(
    path: str | Path, sync: str = "normal", readonly: bool = False, check: bool = False
) -> sqlite3.Connection:
    """A connection in autocommit mode (transactions are explicit, see :func:`transaction`).

    A database that cannot be opened (read-only or full data dir, a directory in its
    place...) raises :class:`StorageError` naming the file; a damaged one
    :class:`DatabaseCorrupt` (with ``check``, also damage that opening alone does not
    meet: :func:`check_integrity`).
    """
    p = Path(path)
    conn = None
    try:
        if readonly:
            conn = sqlite3.connect(
                f"file:{p}?mode=ro", uri=True, isolation_level=None, check_same_thread=False
            )
        else:
            p.parent.mkdir(parents=True, exist_ok=True)
            conn = sqlite3.connect(p, isolation_level=None, check_same_thread=False)
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute(f"PRAGMA synchronous={'FULL' if sync == 'full' else 'NORMAL'}")
        conn.execute("PRAGMA busy_timeout=10000")
        if check:
            check_integrity(conn, p)
    except (sqlite3.Error, DatabaseCorrupt) as exc:
        if conn is not None:
            conn.close()
        if isinstance(exc, DatabaseCorrupt):
            raise
        if is_corruption(exc):
            raise DatabaseCorrupt(p, str(exc)) from exc
        raise StorageError(
            f"{p}: cannot open the database: {exc}", is_storage_failure(exc)
        ) from exc
    return conn


class Participant(Protocol):
    """Something holding in-memory state that must follow a transaction's outcome."""

    def on_commit(self) -> None: ...
    def on_rollback(self) -> None: ...


@contextmanager
def transaction(
    conn: sqlite3.Connection, participants: Sequence[Participant] = ()
) -> Iterator[None]:
    """BEGIN IMMEDIATE ... COMMIT; participants learn the outcome.

    A storage failure (disk full, read-only file) is raised as :class:`StorageError`
    after rolling back, so callers refuse the work instead of acknowledging it (a damaged
    file as :class:`DatabaseCorrupt`, naming it, also when a participant meets the damage
    while it reloads its state on the rollback); any other SQLite error too, with
    ``transient`` False. Participants learn of a rollback
    also when the transaction could not even start.
    """
    try:
        conn.execute("BEGIN IMMEDIATE")
    except sqlite3.Error as exc:
        _roll_back(conn, participants)  # what they staged before the call will not be kept
        if is_corruption(exc):
            raise DatabaseCorrupt(db_file(conn), str(exc)) from exc
        raise StorageError(f"cannot start a transaction: {exc}") from exc  # never the work's fault
    try:
        yield
        conn.execute("COMMIT")
    except BaseException as exc:
        try:
            conn.execute("ROLLBACK")
        except sqlite3.Error:
            pass
        _roll_back(conn, participants)
        if isinstance(exc, sqlite3.Error) and is_corruption(exc):
            raise DatabaseCorrupt(db_file(conn), str(exc)) from exc
        if isinstance(exc, sqlite3.Error):
            raise StorageError(f"storage failed: {exc}", is_storage_failure(exc)) from exc
        raise
    for p in participants:
        p.on_commit()


def _roll_back(conn: sqlite3.Connection, participants: Sequence[Participant]) -> None:
    """Tell every participant of a rollback; once all were told, one that met a damaged file
    while it reloaded its state raises :class:`DatabaseCorrupt`, one that met any other
    storage error :class:`StateLost` (its memory no longer matches the file)."""
    damage: sqlite3.Error | None = None
    lost: sqlite3.Error | None = None
    for p in participants:
        try:
            p.on_rollback()
        except sqlite3.Error as exc:
            if is_corruption(exc):
                damage = damage or exc
            else:
                lost = lost or exc
    if damage is not None:
        raise DatabaseCorrupt(db_file(conn), str(damage)) from damage
    if lost is not None:
        raise StateLost(f"{db_file(conn)}: state not reloaded after a rollback: {lost}") from lost


class Meta:
    """Key/value settings of a data dir (instance id, schema version, zoom...)."""

    def __init__(self, conn: sqlite3.Connection):
        self._conn = conn
        conn.execute("CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")

    def get(self, key: str) -> str | None:
        row = self._conn.execute("SELECT value FROM meta WHERE key=?", (key,)).fetchone()
        return None if row is None else str(row[0])

    def setdefault(self, key: str, value: str) -> str:
        """The stored value, storing ``value`` first if there is none."""
        self._conn.execute("INSERT OR IGNORE INTO meta(key, value) VALUES (?, ?)", (key, value))
        got = self.get(key)
        assert got is not None
        return got

    def set(self, key: str, value: str) -> None:
        self._conn.execute("INSERT OR REPLACE INTO meta(key, value) VALUES (?, ?)", (key, value))


def u64_to_i64(a: np.ndarray) -> np.ndarray:
    """SQLite integers are signed 64-bit: store u64 ids by reinterpretation."""
    return np.ascontiguousarray(a, dtype=np.uint64).view(np.int64)


def i64_to_u64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.int64).view(np.uint64)


def id_to_sql(v: int) -> int:
    """One u64 id as SQLite's signed integer (:func:`u64_to_i64` for a scalar).

    >>> id_to_sql(2**64 - 1), id_from_sql(-1)
    (-1, 18446744073709551615)
    """
    return int(u64_to_i64(np.array([v], np.uint64))[0])


def id_from_sql(v: int) -> int:
    """Inverse of :func:`id_to_sql`."""
    return int(i64_to_u64(np.array([v], np.int64))[0])

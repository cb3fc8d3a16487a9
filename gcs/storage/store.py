"""The daemon's durable state in one SQLite file (WAL): agent registry, missions, progress, events.

Why SQLite: a daemon killed mid-mission must come back with the same connection IDs, the
accepted missions, the released sync steps and the event log; one file, no server, crash-safe.
State writes are small and synchronous (WAL, synchronous=NORMAL: tens of microseconds each), so
they run on the event loop. Bulk telemetry is not: its inserts and pruning run in the telemetry
writer thread on its own connection (gcs/observe/telemetry.py), and history reads run in worker threads
on read-only connections (:meth:`Store.reader`, :func:`telemetry_page`); WAL lets readers run
beside the writer. Bulk statements are chunked so no transaction holds the write lock for long.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import os
import sqlite3
import threading
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gcs.missions.release_journal import JournalError, ReleaseJournal, SkipLog

log = logging.getLogger(__name__)

SCHEMA_VERSION = 4
MAX_CID = 65_535  # the wire's cid range (docs/protocol.md, type 1)


class StoreError(RuntimeError):
    """The database cannot be used safely (damaged, or missing where one existed)."""


class CidExhausted(Exception):
    """Every connection ID is taken: a new identity is refused, never given a duplicate."""


_MIGRATIONS: dict[int, str] = {
    1: """
    CREATE TABLE agents (
        identity TEXT PRIMARY KEY,
        cid INTEGER UNIQUE NOT NULL,
        first_seen REAL NOT NULL,
        last_seen REAL NOT NULL,
        capabilities TEXT NOT NULL DEFAULT '{}'
    );
    CREATE TABLE missions (
        id TEXT PRIMARY KEY,
        name TEXT NOT NULL,
        task TEXT NOT NULL,
        state TEXT NOT NULL,
        created REAL NOT NULL,
        finished REAL,
        result TEXT
    );
    CREATE TABLE mission_agents (
        mission_id TEXT NOT NULL REFERENCES missions(id),
        agent TEXT NOT NULL,
        completed_step INTEGER NOT NULL DEFAULT -1,
        excluded INTEGER NOT NULL DEFAULT 0,
        PRIMARY KEY (mission_id, agent)
    );
    CREATE TABLE releases (
        mission_id TEXT NOT NULL REFERENCES missions(id),
        step INTEGER NOT NULL,
        released_at REAL NOT NULL,
        PRIMARY KEY (mission_id, step)
    );
    CREATE TABLE events (
        id INTEGER PRIMARY KEY AUTOINCREMENT,
        time REAL NOT NULL,
        kind TEXT NOT NULL,
        severity TEXT NOT NULL,
        agent TEXT,
        mission_id TEXT,
        message TEXT NOT NULL,
        data TEXT NOT NULL DEFAULT '{}'
    );
    CREATE INDEX events_kind ON events(kind);
    """,
    2: """
    CREATE TABLE telemetry (
        id INTEGER PRIMARY KEY AUTOINCREMENT,
        agent TEXT NOT NULL,
        time REAL NOT NULL,
        received REAL NOT NULL,
        lat REAL NOT NULL, lon REAL NOT NULL, alt_rel REAL NOT NULL, alt_amsl REAL NOT NULL,
        vn REAL NOT NULL, ve REAL NOT NULL, vd REAL NOT NULL, heading_deg REAL NOT NULL,
        battery_pct REAL, voltage_v REAL, current_a REAL,
        mode TEXT NOT NULL, armed INTEGER NOT NULL, landed INTEGER NOT NULL,
        gps_fix INTEGER NOT NULL, satellites INTEGER NOT NULL,
        step INTEGER NOT NULL, mission_id TEXT, buffered INTEGER NOT NULL
    );
    CREATE INDEX telemetry_agent_time ON telemetry(agent, time);
    CREATE INDEX telemetry_received ON telemetry(received);
    """,
    3: """
    CREATE TABLE vehicle_holds (
        agent TEXT NOT NULL,
        owner TEXT NOT NULL,
        reason TEXT NOT NULL,
        since REAL NOT NULL,
        PRIMARY KEY (agent, owner)
    );
    ALTER TABLE missions ADD COLUMN paused INTEGER NOT NULL DEFAULT 0;
    """,
    4: """
    CREATE TABLE survey_records (
        mission_id TEXT PRIMARY KEY,
        updated REAL NOT NULL,
        record BLOB NOT NULL
    );
    """,
}


def _migrate(db: sqlite3.Connection, path: str) -> None:
    """Bring the schema to :data:`SCHEMA_VERSION`; a newer one is refused (written by a newer daemon)."""
    version = db.execute("PRAGMA user_version").fetchone()[0]
    if version > SCHEMA_VERSION:
        raise StoreError(
            f"{path} has schema version {version}, newer than this daemon's {SCHEMA_VERSION} "
            "(written by a newer fleetgcs): run that version, or restore a backup this one wrote"
        )
    for target in range(version + 1, SCHEMA_VERSION + 1):
        db.executescript(f"BEGIN; {_MIGRATIONS[target]} PRAGMA user_version={target}; COMMIT;")


@functools.cache
def _expected_schema() -> dict[str, frozenset[str]]:
    """Table -> column names every migration together creates (built once, in memory)."""
    db = sqlite3.connect(":memory:", isolation_level=None)
    try:
        _migrate(db, ":memory:")
        return _schema_of(db)
    finally:
        db.close()


def _schema_of(db: sqlite3.Connection) -> dict[str, frozenset[str]]:
    tables = [r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")]
    return {
        t: frozenset(str(c[1]) for c in db.execute(f"PRAGMA table_info({t!r})"))
        for t in tables
        if not t.startswith("sqlite_")
    }


def _check_schema(db: sqlite3.Connection, path: str) -> None:
    """Every table and column this daemon uses is there (a dropped table fails here, not mid-flight)."""
    have = _schema_of(db)
    for table, columns in sorted(_expected_schema().items()):
        if table not in have:
            raise StoreError(f"{path}: table {table} is missing (damaged database); restore it from a backup")
        missing = sorted(columns - have[table])
        if missing:
            raise StoreError(
                f"{path}: table {table} lacks column(s) {', '.join(missing)} (damaged database); "
                "restore it from a backup"
            )


def _prepare_file(file: Path, allow_new: bool) -> None:
    """Refuse a path that cannot be this fleet's database file; create a new one where allowed.

    A new database is one the daemon makes itself (:func:`_create_database`): a missing file in a
    data directory that never had one, or, with ``allow_new`` (``--new-fleet``), a missing file
    whose marker says one existed, or a zero-length file.
    """
    marker = file.with_name(file.name + ".created")
    if not file.parent.exists():
        try:
            file.parent.mkdir(mode=0o700, parents=True)
        except OSError as exc:
            raise StoreError(f"cannot create the data directory {file.parent}: {exc}") from None
    elif not file.parent.is_dir():
        raise StoreError(f"{file.parent} is not a directory (the database goes in it)")
    if file.exists() and not file.is_file():
        raise StoreError(f"{file} is a directory or device, not a database file; give another --data-dir")
    if file.exists() and file.stat().st_size == 0:
        if not allow_new:
            raise StoreError(
                f"{file} is empty (zero bytes), not this fleet's database; restore it from a backup, or "
                "start with --new-fleet to begin a new fleet there (connection IDs will be assigned anew)"
            )
        file.unlink()
    if not file.exists():
        if marker.exists() and not allow_new:
            raise StoreError(
                f"{file} is missing but a database existed there (marker {marker.name}); restore it "
                "from a backup, or start with --new-fleet to begin a new fleet "
                "(connection IDs will be assigned anew)"
            )
        try:
            _create_database(file)
            marker.write_text("fleetgcs database created here; see docs/security.md\n")
        except (OSError, sqlite3.Error) as exc:
            raise StoreError(f"cannot create the database {file}: {exc}") from None
    with contextlib.suppress(OSError):
        os.chmod(file, 0o600)  # the WAL and shared-memory files take the database's mode


def _create_database(file: Path) -> None:
    """A new database with its full schema, under a temporary name renamed into place: a file
    at the database's name is never empty or schema-less (either is refused as not ours)."""
    temporary = file.with_name(file.name + ".new")
    for leftover in (temporary, *(file.with_name(file.name + s) for s in ("-wal", "-shm"))):
        leftover.unlink(missing_ok=True)  # an old WAL must never be applied to the new file
    os.close(os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    db = sqlite3.connect(temporary, isolation_level=None)
    try:
        _migrate(db, str(temporary))
    finally:
        db.close()
    temporary.with_name(temporary.name + "-journal").unlink(missing_ok=True)
    os.replace(temporary, file)


TELEMETRY_COLUMNS = (
    "agent",
    "time",
    "received",
    "lat",
    "lon",
    "alt_rel",
    "alt_amsl",
    "vn",
    "ve",
    "vd",
    "heading_deg",
    "battery_pct",
    "voltage_v",
    "current_a",
    "mode",
    "armed",
    "landed",
    "gps_fix",
    "satellites",
    "step",
    "mission_id",
    "buffered",
)


@dataclass(frozen=True, slots=True)
class StoredMission:
    id: str
    name: str
    task_json: str
    state: str
    created: float
    finished: float | None
    result: str | None


@dataclass(frozen=True, slots=True)
class StoredEvent:
    id: int
    time: float
    kind: str
    severity: str
    agent: str | None
    mission_id: str | None
    message: str
    data: dict[str, Any]


class Store:
    """Thin, explicit SQL over one connection; every public method is one transaction."""

    def __init__(self, path: Path | str, *, allow_new: bool = False, read_only: bool = False) -> None:
        """Open (or create) the database at ``path``.

        Refuses (:class:`StoreError`, one line for the operator) what cannot be this fleet's
        database: a path that is not a file, a zero-length or foreign file, a schema newer than
        this daemon's or with a table or column missing, a damaged file; and a missing database
        where one existed before (its ``.created`` marker is there). A new database would hand out
        the connection IDs again from 1, so a task file addressed by CID would command other
        vehicles. ``allow_new`` (``gcs serve --new-fleet``) is the operator saying a new fleet is
        what they want (for a missing or zero-length file; a foreign one is never overwritten).
        The directory is created 0700 and the database files are 0600.

        ``read_only`` (``gcs log`` beside a running daemon): nothing is created, migrated or
        recovered; the file must already be at this version's schema.
        """
        self.path = str(path)
        self.read_only = read_only
        if self.path != ":memory:" and not read_only:
            try:
                _prepare_file(Path(self.path), allow_new)
            except OSError as exc:
                raise StoreError(f"cannot use the database path {self.path}: {exc}") from None
        try:
            if read_only:
                uri = Path(self.path).resolve().as_uri() + "?mode=ro"
                self._db = sqlite3.connect(uri, uri=True, isolation_level=None, check_same_thread=False)
            else:
                self._db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        except sqlite3.Error as exc:
            raise StoreError(f"cannot open the database {self.path}: {exc}") from None
        self.journal: ReleaseJournal | None = None
        # Held around every write transaction in this process (the loop's small ones and the
        # telemetry writer's chunks): a writer waiting here is woken the moment the other is
        # done, where SQLite's own busy handler would sleep in growing steps (up to 100 ms).
        self.write_lock = threading.RLock()  # re-entrant: single writes inside an atomic() block
        # Set while a state write waits for the lock: the telemetry writer ends its chunk at the
        # next row (insert_telemetry), so the event loop waits one row, not a chunk.
        self.write_wanted = threading.Event()
        try:
            self._open()
        except StoreError:
            self._close_quietly()
            raise
        except sqlite3.DatabaseError as exc:
            self._close_quietly()
            raise StoreError(
                f"{self.path} is damaged or not a fleetgcs database ({exc}); restore it from a backup"
            ) from None

    def _open(self) -> None:
        """Check the file is this fleet's database, bring its schema up to date, recover releases."""
        if self.read_only:
            self._open_read_only()
            return
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.execute("PRAGMA foreign_keys=ON")
        check = self._db.execute("PRAGMA quick_check").fetchone()[0]
        if check != "ok":
            raise sqlite3.DatabaseError(check)
        if self.path != ":memory:" and self._db.execute("PRAGMA user_version").fetchone()[0] == 0:
            # Every database this daemon creates has its schema before it gets its name
            # (_create_database): one at version 0 is someone else's, or was emptied.
            tables = self._db.execute("SELECT count(*) FROM sqlite_master").fetchone()[0]
            what = (
                f"a SQLite file with {tables} table(s) of something else"
                if tables
                else "an empty SQLite file"
            )
            raise StoreError(
                f"{self.path} is not a fleetgcs database ({what}); give another --data-dir, or move it aside"
            )
        _migrate(self._db, self.path)
        _check_schema(self._db, self.path)
        if self.path != ":memory:":
            journal = Path(self.path + "-releases")
            try:
                self.journal = ReleaseJournal(journal)
            except OSError as exc:
                raise StoreError(f"cannot open the release journal {journal}: {exc}") from None
            self.recover_releases()

    def _open_read_only(self) -> None:
        """A reader's checks: this fleet's database at this version's schema; no write of any kind."""
        check = self._db.execute("PRAGMA quick_check").fetchone()[0]
        if check != "ok":
            raise sqlite3.DatabaseError(check)
        version = self._db.execute("PRAGMA user_version").fetchone()[0]
        if version == 0:
            raise StoreError(f"{self.path} is not a fleetgcs database")
        if version != SCHEMA_VERSION:
            raise StoreError(
                f"{self.path} has schema version {version}, this fleetgcs reads {SCHEMA_VERSION}: "
                + (
                    "run `gcs serve` once to bring it up to date"
                    if version < SCHEMA_VERSION
                    else "use that version"
                )
            )
        _check_schema(self._db, self.path)

    def _close_quietly(self) -> None:
        if self.journal is not None:
            with contextlib.suppress(OSError):
                self.journal.close()
            self.journal = None
        self._db.close()

    def close(self) -> None:
        if self.journal is not None:
            self.journal.close()
        self._db.close()

    # --- agents ---------------------------------------------------------------------------------

    def cid_of(self, identity: str) -> int | None:
        """The connection ID ``identity`` already has, or None if it never joined (not enrolled)."""
        row = self._db.execute("SELECT cid FROM agents WHERE identity=?", (identity,)).fetchone()
        return None if row is None else int(row[0])

    def cid_for(self, identity: str, capabilities: dict[str, Any]) -> int:
        """The stable connection ID of ``identity``, allocating the next free one on first contact."""
        now = time.time()
        with self.atomic():
            row = self._db.execute("SELECT cid FROM agents WHERE identity=?", (identity,)).fetchone()
            if row is not None:
                self._db.execute(
                    "UPDATE agents SET last_seen=?, capabilities=? WHERE identity=?",
                    (now, json.dumps(capabilities), identity),
                )
                return int(row[0])
            next_cid = self._db.execute("SELECT COALESCE(MAX(cid), 0) + 1 FROM agents").fetchone()[0]
            if next_cid > MAX_CID:
                raise CidExhausted(
                    f"all {MAX_CID} connection IDs are taken; retire identities (gcs agents retire) first"
                )
            self._db.execute(
                "INSERT INTO agents(identity, cid, first_seen, last_seen, capabilities) VALUES (?,?,?,?,?)",
                (identity, next_cid, now, now, json.dumps(capabilities)),
            )
            return int(next_cid)

    def identity_for_cid(self, cid: int) -> str | None:
        row = self._db.execute("SELECT identity FROM agents WHERE cid=?", (cid,)).fetchone()
        return None if row is None else str(row[0])

    def known_agents(self) -> dict[str, int]:
        return {str(i): int(c) for i, c in self._db.execute("SELECT identity, cid FROM agents")}

    # --- missions -------------------------------------------------------------------------------

    def add_mission(self, mission_id: str, name: str, task_json: str, agents: list[str]) -> None:
        with self.atomic():
            self._db.execute(
                "INSERT INTO missions(id, name, task, state, created) VALUES (?,?,?,?,?)",
                (mission_id, name, task_json, "running", time.time()),
            )
            self._db.executemany(
                "INSERT INTO mission_agents(mission_id, agent) VALUES (?,?)",
                [(mission_id, a) for a in agents],
            )

    def finish_mission(self, mission_id: str, state: str, result: str) -> None:
        self._write(
            "UPDATE missions SET state=?, finished=?, result=? WHERE id=?",
            (state, time.time(), result, mission_id),
        )

    def mission(self, mission_id: str) -> StoredMission | None:
        row = self._db.execute(
            "SELECT id, name, task, state, created, finished, result FROM missions WHERE id=?", (mission_id,)
        ).fetchone()
        return None if row is None else StoredMission(*row)

    def missions(self, state: str | None = None) -> list[StoredMission]:
        sql = "SELECT id, name, task, state, created, finished, result FROM missions"
        rows = (
            self._db.execute(sql + " WHERE state=? ORDER BY created", (state,))
            if state
            else self._db.execute(sql + " ORDER BY created")
        )
        return [StoredMission(*r) for r in rows]

    def set_paused(self, mission_id: str, paused: bool) -> None:
        with self.atomic():
            self._db.execute("UPDATE missions SET paused = ? WHERE id = ?", (int(paused), mission_id))

    def paused_missions(self) -> set[str]:
        rows = self._db.execute("SELECT id FROM missions WHERE paused = 1 AND state = 'running'").fetchall()
        return {row[0] for row in rows}

    def save_hold(self, agent: str, owner: str, reason: str) -> None:
        """An operator-level hold, kept across daemon restarts (the lower ones are recomputed)."""
        with self.atomic():
            self._db.execute(
                "INSERT OR REPLACE INTO vehicle_holds (agent, owner, reason, since) VALUES (?, ?, ?, ?)",
                (agent, owner, reason, time.time()),
            )

    def drop_hold(self, agent: str, owner: str) -> None:
        with self.atomic():
            self._db.execute("DELETE FROM vehicle_holds WHERE agent = ? AND owner = ?", (agent, owner))

    def holds(self) -> list[tuple[str, str, str]]:
        """(agent, owner, reason) of every persisted hold."""
        return [
            (r[0], r[1], r[2]) for r in self._db.execute("SELECT agent, owner, reason FROM vehicle_holds")
        ]

    def set_completed_step(self, mission_id: str, agent: str, step: int) -> None:
        self._write(
            "UPDATE mission_agents SET completed_step=MAX(completed_step, ?) WHERE mission_id=? AND agent=?",
            (step, mission_id, agent),
        )

    def exclude_agent(self, mission_id: str, agent: str) -> None:
        self._write(
            "UPDATE mission_agents SET excluded=1 WHERE mission_id=? AND agent=?", (mission_id, agent)
        )

    def mission_agents(self, mission_id: str) -> dict[str, tuple[int, bool]]:
        """agent -> (completed_step, excluded)."""
        rows = self._db.execute(
            "SELECT agent, completed_step, excluded FROM mission_agents WHERE mission_id=?", (mission_id,)
        )
        return {str(a): (int(s), bool(e)) for a, s, e in rows}

    def journal_release(self, mission_id: str, step: int) -> float:
        """The release of ``step`` made durable before it is sent (:mod:`gcs.missions.release_journal`): one
        append, no lock, no transaction. Its row follows with :meth:`record_release`; returns the
        release time to give it."""
        at = time.time()
        if self.journal is not None:
            try:
                self.journal.append(mission_id, step, at)
            except OSError as exc:  # a full disk: the database makes it durable instead (slower)
                where = self.journal.path
                log.error("release journal %s: %s; the release goes to the database first", where, exc)
                self.record_release(mission_id, step, at)
        return at

    def record_release(self, mission_id: str, step: int, at: float | None = None) -> None:
        """The release row (inside the caller's transaction, with its event): after a
        :meth:`journal_release`, :meth:`release_recorded` once it is committed."""
        self._write(
            "INSERT OR IGNORE INTO releases(mission_id, step, released_at) VALUES (?,?,?)",
            (mission_id, step, time.time() if at is None else at),
        )

    def release_recorded(self) -> None:
        """The journaled release's row is committed (the journal may be emptied)."""
        if self.journal is not None:
            self.journal.recorded()

    def recover_releases(self) -> list[tuple[str, int]]:
        """Releases journaled but not in the database (the daemon died between the two): written
        now, each with its ``sync_released`` event, in one transaction; then the journal is
        emptied. Returns what was recovered.

        The journal is not trusted blindly (docs/security.md): a line that is not a release this
        daemon could have written is skipped (:mod:`gcs.missions.release_journal`), and so is one naming a
        mission the database does not hold, or a barrier some non-excluded member of the mission
        had not finished as stored in the database (``mission_agents.completed_step``): recovering
        it would let a drone fly past a barrier another had not reached. Each is warned about
        naming its line (the first few; then one summary), and the file is kept as
        ``<journal>.rejected`` for the operator. Bounded: one query for the mission list, two per
        mission named, none per line.
        """
        if self.journal is None:
            return []
        skips = SkipLog(self.journal.path)
        known = {str(r[0]) for r in self._db.execute("SELECT id FROM missions")}
        try:
            entries = self.journal.entries(skips, missions=known)
        except OSError as exc:  # refuse to start rather than forget a release agents acted on
            raise StoreError(f"cannot read the release journal {self.journal.path}: {exc}") from None
        except JournalError as exc:
            raise StoreError(f"the release journal {self.journal.path} is refused: {exc}") from None
        released: dict[str, set[int]] = {}
        members: dict[str, dict[str, int]] = {}
        recovered: list[tuple[str, int]] = []
        with self.atomic():
            for entry in entries:
                mission_id, step = entry.mission_id, entry.step
                done = released.setdefault(mission_id, self.released_steps(mission_id))
                if step in done:
                    continue
                if mission_id not in members:
                    members[mission_id] = {
                        a: s for a, (s, out) in self.mission_agents(mission_id).items() if not out
                    }
                behind = sorted(a for a, completed in members[mission_id].items() if completed < step)
                if behind or not members[mission_id]:
                    who = f"{', '.join(behind[:5])}{' ...' if len(behind) > 5 else ''} had not finished it"
                    skips.skip(
                        entry.line,
                        f"release of step {step} of mission {mission_id} NOT recovered: "
                        + (
                            f"{who} as stored in the database" if behind else "the mission has no member left"
                        ),
                    )
                    continue
                self.record_release(mission_id, step, entry.at)
                self.add_event(
                    "sync_released",
                    "info",
                    f"step {step} released (recovered from the release journal after a restart)",
                    mission_id=mission_id,
                    data={"step": step, "recovered": True},
                    at=entry.at,
                )
                done.add(step)
                recovered.append((mission_id, step))
        skips.summary()
        if skips.skipped:
            try:
                self.journal.set_aside()
            except OSError as exc:  # a full disk: the warnings above are what is left of them
                log.warning(
                    "release journal %s: could not keep the skipped lines (%s)", self.journal.path, exc
                )
        self.journal.clear()
        return recovered

    def released_steps(self, mission_id: str) -> set[int]:
        return {
            int(r[0]) for r in self._db.execute("SELECT step FROM releases WHERE mission_id=?", (mission_id,))
        }

    # --- survey records (issue 27) ----------------------------------------------------------------

    def save_survey_record(self, mission_id: str, record: bytes, keep: int) -> None:
        """A survey's coverage record (gcs/missions/record_codec.py), replacing its older copy; only
        the ``keep`` newest records stay."""
        with self.atomic():
            self._db.execute(
                "INSERT INTO survey_records(mission_id, updated, record) VALUES (?,?,?) "
                "ON CONFLICT(mission_id) DO UPDATE SET updated=excluded.updated, record=excluded.record",
                (mission_id, time.time(), record),
            )
            self._db.execute(
                "DELETE FROM survey_records WHERE mission_id NOT IN "
                "(SELECT mission_id FROM survey_records ORDER BY updated DESC LIMIT ?)",
                (max(1, keep),),
            )

    def survey_record(self, mission_id: str) -> bytes | None:
        row = self._db.execute(
            "SELECT record FROM survey_records WHERE mission_id=?", (mission_id,)
        ).fetchone()
        return None if row is None else bytes(row[0])

    # --- events ---------------------------------------------------------------------------------

    def add_event(
        self,
        kind: str,
        severity: str,
        message: str,
        agent: str | None = None,
        mission_id: str | None = None,
        data: dict[str, Any] | None = None,
        at: float | None = None,
    ) -> StoredEvent:
        when = time.time() if at is None else at
        payload = data or {}
        cur = self._write(
            "INSERT INTO events(time, kind, severity, agent, mission_id, message, data) "
            "VALUES (?,?,?,?,?,?,?)",
            (when, kind, severity, agent, mission_id, message, json.dumps(payload)),
        )
        return StoredEvent(int(cur.lastrowid or 0), when, kind, severity, agent, mission_id, message, payload)

    def events(
        self, since_id: int = 0, kind: str | None = None, agent: str | None = None, limit: int = 500
    ) -> list[StoredEvent]:
        sql = "SELECT id, time, kind, severity, agent, mission_id, message, data FROM events WHERE id > ?"
        args: list[Any] = [since_id]
        if kind:
            sql += " AND kind = ?"
            args.append(kind)
        if agent:
            sql += " AND agent = ?"
            args.append(agent)
        sql += " ORDER BY id LIMIT ?"
        args.append(max(1, min(limit, 10_000)))
        return [
            StoredEvent(int(r[0]), r[1], r[2], r[3], r[4], r[5], r[6], json.loads(r[7]))
            for r in self._db.execute(sql, args)
        ]

    # --- telemetry ------------------------------------------------------------------------------

    def reader(self) -> sqlite3.Connection:
        """A new read-only connection to the same file, for a query run in another thread."""
        if self.path == ":memory:":
            raise ValueError("an in-memory store has no second connection")
        db = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True, check_same_thread=False)
        db.execute("PRAGMA query_only=ON")
        return db

    def writer(self) -> sqlite3.Connection:
        """A new read-write connection to the same file, for the telemetry writer thread."""
        if self.path == ":memory:":
            raise ValueError("an in-memory store has no second connection")
        db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False, timeout=30.0)
        db.execute("PRAGMA synchronous=NORMAL")
        # WAL checkpoints become the bulk writer's job, run outside any write transaction
        # (:func:`checkpoint`): a commit that crosses the auto-checkpoint threshold would copy
        # megabytes inside the commit, on whichever connection (possibly the loop's) made it.
        db.execute("PRAGMA wal_autocheckpoint=0")
        self._db.execute("PRAGMA wal_autocheckpoint=0")
        return db

    def add_telemetry(self, rows: Iterable[tuple[Any, ...]]) -> None:
        """Insert rows in ``TELEMETRY_COLUMNS`` order (chunked transactions)."""
        insert_telemetry(self._db, rows, self.write_lock, self.write_wanted)

    def telemetry(
        self,
        agent: str,
        since: float = 0.0,
        until: float = float("inf"),
        mission_id: str | None = None,
        limit: int = 1_000_000,
    ) -> list[dict[str, Any]]:
        """Stored samples of ``agent`` with agent time in [since, until], oldest first."""
        sql = f"SELECT {','.join(TELEMETRY_COLUMNS)} FROM telemetry WHERE agent=? AND time>=? AND time<=?"
        args: list[Any] = [agent, since, until if until != float("inf") else 1e18]
        if mission_id is not None:
            sql += " AND mission_id=?"
            args.append(mission_id)
        sql += " ORDER BY time, id LIMIT ?"
        args.append(limit)
        return [dict(zip(TELEMETRY_COLUMNS, row, strict=True)) for row in self._db.execute(sql, args)]

    def telemetry_page(
        self, agent: str, since: float = 0.0, until: float = float("inf"), limit: int = 1000, every: int = 1
    ) -> list[dict[str, Any]]:
        """:func:`telemetry_page` on this store's own connection (small pages, tests)."""
        return telemetry_page(self._db, agent, since, until, limit, every)

    def telemetry_agents(self) -> list[str]:
        return [str(r[0]) for r in self._db.execute("SELECT DISTINCT agent FROM telemetry ORDER BY agent")]

    def prune_telemetry(self, older_than: float) -> int:
        """Delete samples received before ``older_than`` (UNIX time); returns how many."""
        return prune_telemetry(self._db, older_than, self.write_lock)

    @contextlib.contextmanager
    def write_priority(self) -> Iterator[None]:
        """Hold the write lock, a bulk writer (telemetry) giving it up within one row.

        Why: the telemetry writer thread binds each row with the GIL held and releases it around
        each ``sqlite3_step``, so next to a busy event loop it waits for the GIL at every row,
        holding the write lock all the while: measured at 1,000 agents, a 128-row chunk held it
        ~9 ms (1.7 ms of CPU), up to 90 ms, and the event loop's state writes (a barrier release,
        a completed step, an event) waited as long. With ``write_wanted`` set the writer's chunk
        commits after its next row. Every state write of this store takes the lock this way.
        """
        self.write_wanted.set()
        try:
            with self.write_lock:
                self.write_wanted.clear()  # the writer's next chunk now waits on the lock itself
                yield
        finally:
            self.write_wanted.clear()

    def _write(self, sql: str, args: Any = ()) -> sqlite3.Cursor:
        """One write statement (its own transaction) under the process's write lock."""
        with self.write_priority():
            return self._db.execute(sql, args)

    @contextlib.contextmanager
    def atomic(self) -> Iterator[None]:
        """Several of this store's writes as one transaction: a crash keeps all of them or none."""
        with self.write_priority(), _Transaction(self._db, self.write_lock):
            yield


WriteLock = threading.RLock
"""The store's write lock type (shared with the telemetry writer thread's connection)."""

TELEMETRY_CHUNK = 500
"""Rows per write transaction: bounds how long a bulk write holds SQLite's single write lock
(a few milliseconds), so the event loop's small state writes never wait long for it."""


_BUFFERED_PARAM = f"?{TELEMETRY_COLUMNS.index('buffered') + 1}"
_INSERT_TELEMETRY = (
    f"INSERT INTO telemetry({','.join(TELEMETRY_COLUMNS)}) "
    f"SELECT {','.join(f'?{n}' for n in range(1, len(TELEMETRY_COLUMNS) + 1))} "
    f"WHERE {_BUFFERED_PARAM} = 0 OR NOT EXISTS (SELECT 1 FROM telemetry WHERE agent = ?1 AND time = ?2)"
)
"""A replayed (buffered) row the table already holds (same agent and time) is skipped: an agent
sends its replay again until the daemon acknowledges it stored (gcs/observe/telemetry.py), and a daemon
killed after the write but before the acknowledgement gets the same reports twice."""
YIELD_WAIT_S = 0.05
"""The longest a bulk insert waits for a lock a state write asked for before it goes on."""


def _chunk(
    first: tuple[Any, ...], source: Iterator[tuple[Any, ...]], wanted: threading.Event, counts: list[int]
) -> Iterator[tuple[Any, ...]]:
    """``first``, then rows of ``source`` up to :data:`TELEMETRY_CHUNK` in all, ending early (never
    before ``first``) once ``wanted`` is set. ``counts``: [rows handed out, 1 if ``source`` ended];
    a row is taken from ``source`` only to be handed out, so a chunk ended early loses none."""
    counts[0], counts[1] = 1, 0
    yield first
    while counts[0] < TELEMETRY_CHUNK and not wanted.is_set():
        row = next(source, None)
        if row is None:
            counts[1] = 1
            return
        counts[0] += 1
        yield row


def insert_telemetry(
    db: sqlite3.Connection, rows: Iterable[tuple[Any, ...]], lock: WriteLock, wanted: threading.Event
) -> int:
    """Insert rows in ``TELEMETRY_COLUMNS`` order in transactions of at most
    :data:`TELEMETRY_CHUNK` rows, each ended early (after at least one row) when ``wanted`` is set
    (:meth:`Store.write_priority`); how many. ``rows`` is read lazily, a chunk at a time."""
    source = iter(rows)
    written = 0
    counts = [0, 0]
    while not counts[1]:
        first = next(source, None)
        if first is None:
            break
        for _ in range(int(YIELD_WAIT_S / 0.0005)):  # a state write asked for the lock: let it take it
            if not wanted.is_set():
                break
            time.sleep(0.0005)
        with _Transaction(db, lock):
            db.executemany(_INSERT_TELEMETRY, _chunk(first, source, wanted, counts))
        written += counts[0]
    return written


def prune_telemetry(
    db: sqlite3.Connection, older_than: float, lock: WriteLock, max_rows: int = 10_000_000
) -> int:
    """Delete samples received before ``older_than`` in chunks; returns how many (at most ``max_rows``)."""
    removed = 0
    while removed < max_rows:
        with lock:
            count = db.execute(
                "DELETE FROM telemetry WHERE id IN (SELECT id FROM telemetry WHERE received < ? LIMIT ?)",
                (older_than, TELEMETRY_CHUNK),
            ).rowcount
        removed += int(count)
        if count < TELEMETRY_CHUNK:
            break
    return removed


def checkpoint(db: sqlite3.Connection) -> None:
    """Copy the WAL back into the database file as far as readers allow (never blocks writers)."""
    db.execute("PRAGMA wal_checkpoint(PASSIVE)")


def _newest_ids_sql() -> str:
    """The ids of the newest ``limit`` samples in range, every ``every``-th (covering index only)."""
    return (
        "SELECT id FROM ("
        " SELECT id, ROW_NUMBER() OVER (ORDER BY time DESC, id DESC) AS rn FROM telemetry"
        " WHERE agent=? AND time>=? AND time<=? ORDER BY time DESC, id DESC LIMIT ?"
        ") WHERE (rn - 1) % ? = 0"
    )


def _page_args(
    agent: str, since: float, until: float, limit: int, every: int
) -> tuple[str, float, float, int, int]:
    return (agent, since, until if until != float("inf") else 1e18, limit * every, every)


def telemetry_page(
    db: sqlite3.Connection,
    agent: str,
    since: float = 0.0,
    until: float = float("inf"),
    limit: int = 1000,
    every: int = 1,
) -> list[dict[str, Any]]:
    """The newest ``limit`` samples of ``agent`` with agent time in [since, until], every ``every``-th.

    Returned oldest first. Scans at most ``limit * every`` entries of the covering index
    ``(agent, time)``, then reads only the rows it returns, so the cost is bounded by the
    caller's caps, not by the size of the log.
    """
    sql = (
        f"SELECT {','.join(TELEMETRY_COLUMNS)} FROM telemetry WHERE id IN ({_newest_ids_sql()})"
        " ORDER BY time, id"
    )
    rows = db.execute(sql, _page_args(agent, since, until, limit, every))
    return [dict(zip(TELEMETRY_COLUMNS, row, strict=True)) for row in rows]


_SAMPLE_JSON = """json_object(
 'received', received,
 'status', json_object(
  'time', time, 'vehicle_time', json('null'),
  'position', json_object('lat', lat, 'lon', lon, 'alt_rel', alt_rel, 'alt_amsl', alt_amsl),
  'velocity', json_object('vn', vn, 've', ve, 'vd', vd),
  'heading_deg', heading_deg,
  'battery', json_object('pct', battery_pct, 'voltage_v', voltage_v, 'current_a', current_a),
  'mode', mode,
  'armed', json(CASE WHEN armed THEN 'true' ELSE 'false' END),
  'landed', json(CASE WHEN landed THEN 'true' ELSE 'false' END),
  'gps', json_object('fix', gps_fix, 'satellites', satellites),
  'mission_id', mission_id,
  'step', step,
  'completed_step', -1, 'queue_depth', 0, 'waiting_sync', NULL, 'paused', json('false'),
  'exceptions', json('[]'), 'autopilot_link', json('true'),
  'buffered', json(CASE WHEN buffered THEN 'true' ELSE 'false' END),
  'failsafe', json('null'), 'failure', json('null'), 'pilot', json('null')))"""


def telemetry_page_json(
    db: sqlite3.Connection,
    agent: str,
    since: float = 0.0,
    until: float = float("inf"),
    limit: int = 1000,
    every: int = 1,
) -> bytes:
    """:func:`telemetry_page` as a JSON array of status samples (``gcs.observe.live.StatusSample``).

    SQLite builds each sample's JSON (in C, without Python's GIL), so a 10 000-sample page costs
    the calling thread one string per row: the event loop thread is not starved while it runs.
    Fields the log does not keep get the status report's defaults.
    """
    sql = f"SELECT {_SAMPLE_JSON} FROM telemetry WHERE id IN ({_newest_ids_sql()}) ORDER BY time, id"
    rows = db.execute(sql, _page_args(agent, since, until, limit, every))
    return ("[" + ",".join(row[0] for row in rows) + "]").encode()


class _Transaction:
    def __init__(self, db: sqlite3.Connection, lock: WriteLock) -> None:
        self._db = db
        self._lock = lock

    def __enter__(self) -> None:
        self._lock.acquire()
        try:
            self._db.execute("BEGIN")
        except BaseException:
            self._lock.release()
            raise

    def __exit__(self, exc_type: object, *_: object) -> None:
        try:
            self._db.execute("ROLLBACK" if exc_type else "COMMIT")
        finally:
            self._lock.release()

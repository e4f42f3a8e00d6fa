"""Storage of the study: SQLAlchemy 2 models and engine set-up.

Tables
------
``settings``      key/value: generated secrets (cookie key, id-HMAC key) when none is configured.
``participants``  one row per participant id (stored as an HMAC, never the raw id; no IP).
``plan``          the trials assigned to a participant, in presentation order (practice first).
``trials``        one row per answered trial; unique ``(participant_id, trial_index)`` and unique
                  ``client_trial_id``, written insert-or-ignore, so retries never duplicate.

Default database: a SQLite file in WAL mode with ``busy_timeout``; write transactions
use ``BEGIN IMMEDIATE`` so concurrent writers queue instead of failing. Any other
SQLAlchemy URL (e.g. ``postgresql+psycopg://...``) works for hosting.
"""

from __future__ import annotations

import contextlib
import secrets
import threading
from collections.abc import Iterator
from datetime import datetime, timezone

from sqlalchemy import (
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Integer,
    String,
    Text,
    UniqueConstraint,
    create_engine,
    event,
    insert,
    select,
)
from sqlalchemy.engine import Connection, Engine
from sqlalchemy.exc import ArgumentError, IntegrityError, OperationalError
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column, sessionmaker

from camo_base.errors import CamoError


def utcnow() -> datetime:
    """Naive UTC timestamp (SQLite keeps no time zone; every stored time is UTC)."""
    return datetime.now(timezone.utc).replace(tzinfo=None)


class Base(DeclarativeBase):
    pass


class Setting(Base):
    __tablename__ = "settings"
    key: Mapped[str] = mapped_column(String(64), primary_key=True)
    value: Mapped[str] = mapped_column(Text)


class Participant(Base):
    __tablename__ = "participants"
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    token: Mapped[str] = mapped_column(String(64), unique=True, index=True)  # session handle (cookie)
    pid_hmac: Mapped[str] = mapped_column(String(64), unique=True)  # HMAC-SHA256 of the participant id
    id_source: Mapped[str] = mapped_column(String(16))  # prolific | generic | anonymous
    study_id: Mapped[str | None] = mapped_column(String(128), nullable=True)  # Prolific STUDY_ID
    session_hmac: Mapped[str | None] = mapped_column(String(64), nullable=True)  # HMAC of Prolific SESSION_ID
    seed: Mapped[int] = mapped_column(BigInteger)
    time_limit_s: Mapped[float] = mapped_column(Float)
    created_at: Mapped[datetime] = mapped_column(DateTime)
    last_seen_at: Mapped[datetime] = mapped_column(DateTime)
    consent_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    declined_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    demographics_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    age_bracket: Mapped[str | None] = mapped_column(String(32), nullable=True)
    instructions_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    completed_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    completion_code: Mapped[str | None] = mapped_column(String(64), nullable=True)


class PlanItem(Base):
    __tablename__ = "plan"
    participant_id: Mapped[int] = mapped_column(ForeignKey("participants.id"), primary_key=True)
    idx: Mapped[int] = mapped_column(Integer, primary_key=True)
    practice: Mapped[bool] = mapped_column(Boolean)
    stimulus_id: Mapped[str] = mapped_column(String(64))
    reveal_id: Mapped[str] = mapped_column(String(64))
    run: Mapped[str] = mapped_column(String(256))
    scene: Mapped[str] = mapped_column(String(256), index=True)
    object: Mapped[str] = mapped_column(String(256))
    method: Mapped[str] = mapped_column(String(256))  # the run's method (``ours``)
    ablation: Mapped[str] = mapped_column(String(256))  # its ablations: ``none`` or a comma list
    # the condition (optimizer.assets.conditions): id (``ours-without-inpainting``) and label (``w/o Inpainting``)
    condition: Mapped[str] = mapped_column(String(300), index=True)
    label: Mapped[str] = mapped_column(String(300))
    view: Mapped[str] = mapped_column(String(64))
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    # the trial's server-side clock: set by the first POST /api/start (image shown), never reset
    started_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    starts: Mapped[int] = mapped_column(Integer, default=0)  # how often it was shown (reloads count)


#: What a plan item shows, copied into its trial when it is answered (the trial row stands alone in the analysis).
SHOWN_COLUMNS = ("practice", "stimulus_id", "run", "scene", "object", "method", "ablation", "condition", "label", "view")


class Trial(Base):
    __tablename__ = "trials"
    __table_args__ = (UniqueConstraint("participant_id", "trial_index", name="uq_trial_participant_index"),)
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participants.id"), index=True)
    trial_index: Mapped[int] = mapped_column(Integer)
    client_trial_id: Mapped[str] = mapped_column(String(64), unique=True)
    practice: Mapped[bool] = mapped_column(Boolean)
    stimulus_id: Mapped[str] = mapped_column(String(64))
    run: Mapped[str] = mapped_column(String(256))
    scene: Mapped[str] = mapped_column(String(256))
    object: Mapped[str] = mapped_column(String(256))
    method: Mapped[str] = mapped_column(String(256))
    ablation: Mapped[str] = mapped_column(String(256))
    condition: Mapped[str] = mapped_column(String(300))  # id and label as in the plan (see PlanItem)
    label: Mapped[str] = mapped_column(String(300))
    view: Mapped[str] = mapped_column(String(64))
    hit: Mapped[bool] = mapped_column(Boolean)
    timed_out: Mapped[bool] = mapped_column(Boolean)
    click_x: Mapped[int | None] = mapped_column(Integer, nullable=True)  # image pixels (column)
    click_y: Mapped[int | None] = mapped_column(Integer, nullable=True)  # image pixels (row)
    rt_ms: Mapped[float] = mapped_column(Float)  # the page's claim: performance.now() image shown -> click/timeout
    time_limit_s: Mapped[float] = mapped_column(Float)
    display_w: Mapped[float | None] = mapped_column(Float, nullable=True)  # CSS px the image was shown at
    display_h: Mapped[float | None] = mapped_column(Float, nullable=True)
    viewport_w: Mapped[float | None] = mapped_column(Float, nullable=True)  # CSS px of the browser viewport
    viewport_h: Mapped[float | None] = mapped_column(Float, nullable=True)
    dpr: Mapped[float | None] = mapped_column(Float, nullable=True)  # window.devicePixelRatio
    server_received_at: Mapped[datetime] = mapped_column(DateTime)
    # the server's clock, the time the study decides on and reports: ms from the arrival of the trial's first
    # /api/start to this answer's arrival
    server_rt_ms: Mapped[float | None] = mapped_column(Float, nullable=True)
    late: Mapped[bool] = mapped_column(Boolean, default=False)  # a click after the deadline, stored as a timeout
    too_fast: Mapped[bool] = mapped_column(Boolean, default=False)  # server_rt_ms below RT_FLOOR_MS (excluded)
    # the page's rt_ms is more than CLOCK_TOLERANCE_MS below the server's: flagged, judged on the server's time
    clock_mismatch: Mapped[bool] = mapped_column(Boolean, default=False)
    starts: Mapped[int] = mapped_column(Integer, default=1)  # times the image was shown (> 1: reloaded)


# ---------------------------------------------------------------------------
# engine
# ---------------------------------------------------------------------------


def make_engine(url: str, busy_timeout_ms: int = 30000, synchronous: str = "FULL", pool_size: int = 16) -> Engine:
    """Engine for ``url``; SQLite files get WAL, ``busy_timeout`` and ``BEGIN IMMEDIATE`` for writers.

    ``synchronous=FULL`` (default) makes every acknowledged commit durable against power
    loss, not just against a crash of the server process.
    """
    if synchronous.upper() not in ("OFF", "NORMAL", "FULL", "EXTRA"):
        raise CamoError(f"SQLITE_SYNCHRONOUS must be OFF, NORMAL, FULL or EXTRA, not {synchronous!r}")
    try:
        is_sqlite = url.startswith("sqlite")
        # no pool_pre_ping: it costs a round trip per checkout; a connection broken by a database restart
        # raises OperationalError (503, the page retries) and SQLAlchemy then replaces the pool's connections
        kwargs: dict = {"pool_size": pool_size, "max_overflow": pool_size, "pool_recycle": 1800}
        if is_sqlite:
            if url in ("sqlite://", "sqlite:///:memory:"):
                raise CamoError("use a SQLite file (sqlite:///path/study.sqlite), not an in-memory database")
            kwargs["connect_args"] = {"check_same_thread": False, "timeout": busy_timeout_ms / 1000}
        engine = create_engine(url, **kwargs)
    except ArgumentError as exc:
        raise CamoError(f"bad database URL {url!r}: {exc}") from None
    except ModuleNotFoundError as exc:
        raise CamoError(f"database driver for {url.split(':')[0]!r} is not installed ({exc.name})") from None
    if engine.dialect.name == "sqlite":

        @event.listens_for(engine, "connect")
        def _on_connect(dbapi_conn, _record):
            dbapi_conn.isolation_level = None  # we emit BEGIN ourselves (see _on_begin)
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA journal_mode=WAL")
            cur.execute(f"PRAGMA busy_timeout={int(busy_timeout_ms)}")
            cur.execute(f"PRAGMA synchronous={synchronous.upper()}")
            cur.execute("PRAGMA foreign_keys=ON")
            cur.close()

        @event.listens_for(engine, "begin")
        def _on_begin(conn):
            mode = conn.get_execution_options().get("sqlite_begin", "DEFERRED")
            conn.exec_driver_sql(f"BEGIN {mode}")

    return engine


class Database:
    """Engine plus two session factories: ``read()`` and ``write()`` (serialised writers on SQLite)."""

    def __init__(self, url: str, **engine_kwargs):
        self.url = url
        self.engine = make_engine(url, **engine_kwargs)
        self._read = sessionmaker(self.engine, expire_on_commit=False)
        self._write_engine = self.engine.execution_options(sqlite_begin="IMMEDIATE")
        self._read_engine = (self.engine.execution_options(isolation_level="AUTOCOMMIT")
                             if self.engine.dialect.name == "postgresql" else self.engine)
        self._write = sessionmaker(self._write_engine, expire_on_commit=False)
        self._insert_ignore_stmts: dict = {}
        self._write_lock = threading.Lock() if self.engine.dialect.name == "sqlite" else contextlib.nullcontext()
        self._light_engine = None
        if self.engine.dialect.name == "sqlite":  # same file, commits without fsync (see write_light)
            self._light_engine = make_engine(url, **dict(engine_kwargs, synchronous="NORMAL"))
            self._light_write_engine = self._light_engine.execution_options(sqlite_begin="IMMEDIATE")
            self._light = sessionmaker(self._light_write_engine, expire_on_commit=False)
        else:
            if self.engine.dialect.name == "postgresql":

                @event.listens_for(self.engine, "begin")
                def _light_begin(conn):
                    if conn.get_execution_options().get("camo_light"):
                        conn.exec_driver_sql("SET LOCAL synchronous_commit TO OFF")

            self._light_write_engine = self.engine.execution_options(camo_light=True)
            self._light = sessionmaker(self._light_write_engine, expire_on_commit=False)
        try:
            Base.metadata.create_all(self.engine)
        except OperationalError as exc:
            raise CamoError(f"cannot open database {url!r}: {exc.orig}") from None
        check_schema(self.engine, url)

    def read(self) -> Session:
        return self._read()

    @contextlib.contextmanager
    def write(self) -> Iterator[Session]:
        """Session for a write transaction. On SQLite, writers of this process queue on a lock first:
        SQLite's own busy handler sleeps in growing steps, which would show up as latency spikes."""
        with self._write_lock:
            with self._write() as s:
                yield s

    @contextlib.contextmanager
    def write_light(self) -> Iterator[Session]:
        """Write transaction for records whose loss in a power failure is harmless (a trial's start time:
        lost, the page would start a fresh clock). SQLite commits it without fsync (``synchronous=NORMAL``
        in WAL mode: durable against a crash of the server process, not of the machine); PostgreSQL with
        ``synchronous_commit = off`` for that transaction. Trials themselves always use :meth:`write`."""
        with self._write_lock:
            with self._light() as s:
                yield s

    @contextlib.contextmanager
    def read_conn(self) -> Iterator[Connection]:
        """A Core connection for reads (the hot API paths: prebuilt statements, no ORM; see study_site.views). On
        PostgreSQL in autocommit mode: a read is one round trip to the server (no BEGIN, no ROLLBACK on return)."""
        with self._read_engine.connect() as c:
            yield c

    @contextlib.contextmanager
    def write_conn(self, light: bool = False) -> Iterator[Connection]:
        """A Core connection in a write transaction, committed on exit: like :meth:`write` (``light=False``) or
        :meth:`write_light` (``light=True``)."""
        with self._write_lock:
            with (self._light_write_engine if light else self._write_engine).begin() as c:
                yield c

    @property
    def dialect(self) -> str:
        return self.engine.dialect.name

    def setting(self, key: str, factory=lambda: secrets.token_hex(32)) -> str:
        """Value of a setting, created once with ``factory()`` (race-safe across processes)."""
        with self.read() as s:
            row = s.get(Setting, key)
            if row is not None:
                return row.value
        with self.write() as s, s.begin():
            if s.get(Setting, key) is None:
                s.add(Setting(key=key, value=factory()))
        with self.read() as s:
            return s.get(Setting, key).value

    def put_setting(self, key: str, value: str) -> None:
        """Store a setting, replacing an earlier value (e.g. the clock tolerance the server runs with)."""
        with self.write() as s, s.begin():
            row = s.get(Setting, key)
            if row is None:
                s.add(Setting(key=key, value=value))
            elif row.value != value:
                row.value = value

    def insert_ignore(self, session: Session, model, values: dict) -> bool:
        """INSERT that silently does nothing on a unique-key conflict; True if a row was inserted."""
        if self.dialect in ("sqlite", "postgresql"):
            if self.dialect == "sqlite":
                from sqlalchemy.dialects.sqlite import insert as dialect_insert
            else:
                from sqlalchemy.dialects.postgresql import insert as dialect_insert
            res = session.execute(dialect_insert(model).values(**values).on_conflict_do_nothing())
            return bool(res.rowcount)
        try:
            with session.begin_nested():
                session.execute(insert(model).values(**values))
            return True
        except IntegrityError:
            return False

    def insert_ignore_conn(self, conn: Connection, model, values: dict) -> bool:
        """:meth:`insert_ignore` on a Core connection, with the statement built once per table (the trial write's
        hot path)."""
        stmt = self._insert_ignore_stmts.get(model.__tablename__)
        if stmt is None:
            if self.dialect == "sqlite":
                from sqlalchemy.dialects.sqlite import insert as dialect_insert
            elif self.dialect == "postgresql":
                from sqlalchemy.dialects.postgresql import insert as dialect_insert
            else:
                dialect_insert = None
            stmt = dialect_insert(model.__table__).on_conflict_do_nothing() if dialect_insert else False
            self._insert_ignore_stmts[model.__tablename__] = stmt
        if stmt is False:
            try:
                with conn.begin_nested():
                    conn.execute(insert(model.__table__), values)
                return True
            except IntegrityError:
                return False
        return bool(conn.execute(stmt, values).rowcount)

    def dispose(self) -> None:
        self.engine.dispose()
        if self._light_engine is not None:
            self._light_engine.dispose()


def check_schema(engine: Engine, url: str) -> None:
    """CamoError when an existing database lacks columns of this version (made by an older camo)."""
    from sqlalchemy import inspect

    insp = inspect(engine)
    for table in Base.metadata.sorted_tables:
        have = {c["name"] for c in insp.get_columns(table.name)}
        missing = [c.name for c in table.columns if c.name not in have]
        if missing:
            raise CamoError(
                f"database {engine.url.render_as_string(hide_password=True)}: table {table.name} lacks "
                f"{', '.join(missing)} (made by an older camo); use a new database for this study"
            )


def lock_for_assignment(session: Session) -> None:
    """Serialise cell assignment across processes (no-op on SQLite, whose writers are already serial)."""
    if session.bind.dialect.name != "sqlite":
        session.execute(select(Setting).where(Setting.key == "assign_lock").with_for_update()).first()

"""Where a study lives: an SQLite file (the default), any SQLAlchemy database URL, or an Optuna journal file.

Three things about a storage matter to a sweep and live here:

* opening it, with a clear :class:`~sb3_td3x.sweeps.errors.StorageError` when it cannot be reached;
* the heartbeat (database storages only): a worker writes one every ``heartbeat_interval`` seconds while its
  trial runs, and a trial whose worker was killed is marked FAIL once ``grace_period`` seconds pass without one;
* the budget lock: workers count the study's trials and create the next one under a lock that every worker on the
  storage shares, so that together they run exactly ``n_trials``. SQLite and journal files use a lock file beside
  them (one machine, or a shared file system with working ``flock``); PostgreSQL an advisory lock; MySQL
  ``GET_LOCK``.

A database password never reaches a record or a log line: what is shown goes through
:func:`~sb3_td3x.common.redaction.redact`. A URL given without a password takes it from
``SB3_TD3X_STORAGE_PASSWORD`` (any database; PostgreSQL's driver also reads ``PGPASSWORD`` and ``~/.pgpass``).
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import logging
import os
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path

import optuna
from optuna.storages import BaseStorage, JournalStorage, RDBStorage, RetryHeartbeatStaleTrialCallback
from optuna.storages.journal import JournalFileBackend

from sb3_td3x.common.redaction import redact
from sb3_td3x.sweeps.errors import StorageError

logger = logging.getLogger(__name__)

JOURNAL_PREFIX = "journal:"

#: The password of a storage URL written without one (``postgresql://user@host/db``): it then stays out of the
#: command line, where ``ps`` shows it, and out of the launcher's job files.
PASSWORD_ENV = "SB3_TD3X_STORAGE_PASSWORD"
ENCODE_HINT = (
    "percent-encode the password's special characters (@ is %40, : is %3A, / is %2F, % is %25; Python: "
    f"urllib.parse.quote(password, safe='')), or leave it out of the URL and give it in PGPASSWORD or {PASSWORD_ENV}"
)


@dataclass
class StudyStorage:
    """An opened storage, with what a worker needs beside Optuna's own storage object."""

    url: str  #: as the user gave it (with its password): never show it, show :attr:`display_url`
    storage: BaseStorage
    budget_lock: Callable[[], AbstractContextManager[None]]
    heartbeat_interval: int | None  #: ``None`` where the storage has no heartbeat (journal files)
    grace_period: int | None = None  #: seconds without a heartbeat before a trial is stale (twice the interval if unset)

    def heartbeat_settings(self) -> dict[str, int] | None:
        """What decides when a trial is stale, as the study records it; ``None`` without heartbeat."""
        if self.heartbeat_interval is None:
            return None
        grace_period = self.grace_period if self.grace_period is not None else 2 * self.heartbeat_interval
        return {"heartbeat_interval": self.heartbeat_interval, "grace_period": grace_period}

    @property
    def display_url(self) -> str:
        """The URL with its password masked (``***``)."""
        return redact(self.url)

    def dashboard_command(self) -> str:
        """The ``optuna-dashboard`` command for this storage, its password masked (see :meth:`password_hint`)."""
        target = str(journal_path(self.url)) if is_journal(self.url) else self.display_url
        return f"optuna-dashboard {target}"

    def password_hint(self) -> str | None:
        """How to give ``optuna-dashboard`` the password that :meth:`dashboard_command` masks; None without one."""
        if is_journal(self.url) or self.display_url == self.url:
            return None
        from sqlalchemy.engine import make_url

        try:
            parsed = make_url(self.url)
        except Exception:  # noqa: BLE001  (a URL only redact() could read: say it generally)
            parsed = None
        if parsed is not None and parsed.get_backend_name() == "postgresql":
            without = parsed._replace(password=None).render_as_string(hide_password=False)  # set() keeps it
            return (
                "The password is masked (***): give it through the environment, "
                f"PGPASSWORD=<password> optuna-dashboard {without}, or pass the whole URL from a variable, "
                'optuna-dashboard "$STORAGE_URL".'
            )
        return (
            "The password is masked (***): pass the whole URL from an environment variable rather than on the "
            'command line, optuna-dashboard "$STORAGE_URL".'
        )


def is_journal(url: str) -> bool:
    return url.startswith(JOURNAL_PREFIX) or ("://" not in url and url.endswith((".log", ".journal")))


def journal_path(url: str) -> Path:
    return Path(url.removeprefix(JOURNAL_PREFIX).removeprefix("//"))


def default_storage_url(study_dir: Path) -> str:
    """The storage a sweep uses when none is given: ``<study folder>/optuna.db``."""
    return f"sqlite:///{study_dir / 'optuna.db'}"


def open_storage(
    url: str,
    study_name: str,
    heartbeat_interval: int = 60,
    grace_period: int | None = None,
    retry_stale: int = 0,
) -> StudyStorage:
    """Open (and create where needed) the storage at ``url``.

    :param url: ``sqlite:///path.db``, ``postgresql://user:password@host:5432/db``, any other SQLAlchemy URL,
        or ``journal:path.log`` / ``path.log`` for Optuna's journal file; a database URL without a password takes
        the one in ``$SB3_TD3X_STORAGE_PASSWORD``, if set
    :param study_name: names the budget lock, so that studies sharing a database do not wait on each other
    :param heartbeat_interval: seconds between heartbeats of a running trial (database storages)
    :param grace_period: seconds without a heartbeat after which a running trial is marked FAIL;
        Optuna's default is twice the interval
    :param retry_stale: how many times a trial whose worker died is queued again with the same parameters
    """
    if is_journal(url):
        return _open_journal(url, study_name)
    if "://" not in url:
        raise StorageError(
            f"storage {url!r} is neither a database URL nor a journal file: use sqlite:///path/to/study.db, "
            "postgresql://user:<password>@host:5432/dbname, or a journal file such as journal:study.log"
        )
    return _open_rdb(url, study_name, heartbeat_interval, grace_period, retry_stale)


def _open_rdb(url: str, study_name: str, heartbeat_interval: int, grace_period: int | None, retry_stale: int) -> StudyStorage:
    import sqlalchemy.exc
    from sqlalchemy.engine import make_url

    try:
        parsed = make_url(url)
    except (sqlalchemy.exc.ArgumentError, ValueError):  # ValueError: a port that is not a number
        raise StorageError(
            f"storage {redact(url)!r} is not a valid SQLAlchemy URL (dialect://user:<password>@host:port/database; "
            f"{ENCODE_HINT})"
        ) from None
    if "@" in (parsed.host or ""):  # the password's own '@' left as it is: the rest of it was read as the host
        raise StorageError(
            f"storage {redact(url)!r}: its password holds an '@' as it is, so the URL cannot be read; {ENCODE_HINT}"
        )
    backend = parsed.get_backend_name()
    if parsed.password is None and backend != "sqlite" and os.environ.get(PASSWORD_ENV):
        parsed = parsed.set(password=os.environ[PASSWORD_ENV])
        url = parsed.render_as_string(hide_password=False)
    if parsed.drivername == "postgresql" and not _importable("psycopg") and _importable("psycopg2"):
        # SQLAlchemy 2.1 reads postgresql:// as psycopg 3; this package installs psycopg2 (psycopg2-binary)
        parsed = parsed.set(drivername="postgresql+psycopg2")
        url = parsed.render_as_string(hide_password=False)
    engine_kwargs: dict = {"pool_pre_ping": True}  # a long trial outlives idle connections the server drops
    if backend == "sqlite":
        if parsed.database and parsed.database != ":memory:":
            db_path = Path(parsed.database)
            try:
                db_path.parent.mkdir(parents=True, exist_ok=True)
            except OSError as err:
                raise StorageError(f"cannot create the folder of SQLite storage {db_path}: {err.strerror}") from None
        engine_kwargs["connect_args"] = {"timeout": 60}  # wait for other workers' writes instead of failing
    elif backend in ("postgresql", "mysql", "mariadb"):
        engine_kwargs["connect_args"] = {"connect_timeout": 10}
    if grace_period is not None and grace_period <= heartbeat_interval:
        raise StorageError(
            f"grace period ({grace_period}s) must be longer than the heartbeat interval ({heartbeat_interval}s)"
        )
    callback = RetryHeartbeatStaleTrialCallback(max_retry=retry_stale) if retry_stale > 0 else None
    try:
        storage = _create_rdb(url, engine_kwargs, heartbeat_interval, grace_period, callback)
    except sqlalchemy.exc.NoSuchModuleError:
        hint = " (write postgresql://, not postgres://)" if parsed.drivername == "postgres" else ""
        raise StorageError(f"storage {redact(url)!r}: SQLAlchemy has no dialect {parsed.drivername!r}{hint}") from None
    except ImportError:  # Optuna turns a missing driver into "Failed to import DB access module"
        raise StorageError(
            f"storage {redact(url)!r} needs a database driver that is not installed (PostgreSQL: pip install "
            "psycopg2-binary and write postgresql+psycopg2://; MySQL: pip install pymysql and write mysql+pymysql://)"
        ) from None
    except sqlalchemy.exc.SQLAlchemyError as err:
        reason = str(getattr(err, "orig", None) or err).strip().splitlines()[0]
        raise StorageError(
            f"cannot open storage {redact(url)}: {redact(reason)}. Check that the database server is running and "
            "reachable, and that the URL's user, password and database name are right."
        ) from None
    return StudyStorage(url, storage, _rdb_lock(storage, backend, study_name, url), heartbeat_interval, grace_period)


def _importable(module: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(module) is not None


def _create_rdb(url: str, engine_kwargs: dict, heartbeat_interval: int, grace_period: int | None, callback) -> RDBStorage:
    """Optuna's RDBStorage; creating the tables is retried, since workers starting together on a fresh database race."""
    import sqlalchemy.exc

    for attempt in range(3):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
                return RDBStorage(
                    url,
                    engine_kwargs=engine_kwargs,
                    heartbeat_interval=heartbeat_interval,
                    grace_period=grace_period,
                    heartbeat_stale_trial_callback=callback,
                )
        except sqlalchemy.exc.DBAPIError as err:
            # Another process created a table or row between our check and our CREATE: SQLite says "table ... already
            # exists" (OperationalError), PostgreSQL a duplicate key (IntegrityError) or relation (ProgrammingError).
            raced = isinstance(
                err, sqlalchemy.exc.IntegrityError | sqlalchemy.exc.ProgrammingError
            ) or "already exists" in str(err)
            if not raced or attempt == 2:
                raise
            time.sleep(1.0 + attempt)
    raise AssertionError("unreachable")


def _open_journal(url: str, study_name: str) -> StudyStorage:
    path = journal_path(url)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        storage = JournalStorage(JournalFileBackend(str(path)))
    except OSError as err:
        raise StorageError(f"cannot open journal file {path}: {err.strerror}") from None
    logger.info("journal storage %s has no heartbeat: a trial whose worker is killed stays RUNNING", path)
    return StudyStorage(url, storage, lambda: _file_lock(path), heartbeat_interval=None)


def _rdb_lock(storage: RDBStorage, backend: str, study_name: str, url: str) -> Callable[[], AbstractContextManager[None]]:
    if backend == "sqlite":
        database = storage.engine.url.database
        if not database or database == ":memory:":
            return contextlib.nullcontext
        path = Path(database)
        return lambda: _file_lock(path)
    if backend == "postgresql":
        key = int.from_bytes(
            hashlib.blake2b(f"sb3_td3x.sweeps:{study_name}".encode(), digest_size=8).digest(), "big", signed=True
        )
        return lambda: _sql_lock(storage, "SELECT pg_advisory_lock(:key)", "SELECT pg_advisory_unlock(:key)", {"key": key})
    if backend in ("mysql", "mariadb"):
        name = f"sb3_td3x.sweeps:{study_name}"[:64]
        return lambda: _sql_lock(storage, "SELECT GET_LOCK(:name, -1)", "SELECT RELEASE_LOCK(:name)", {"name": name})
    logger.warning(
        "storage %s (%s) has no lock this package knows: workers may together run a few more than n_trials trials",
        redact(url),
        backend,
    )
    return contextlib.nullcontext


@contextlib.contextmanager
def _file_lock(storage_path: Path) -> Iterator[None]:
    lock_path = storage_path.with_name(storage_path.name + ".sweep-lock")
    with open(lock_path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


@contextlib.contextmanager
def _sql_lock(storage: RDBStorage, acquire: str, release: str, params: dict) -> Iterator[None]:
    """A session-level database lock; the server drops it by itself if the worker dies while holding it."""
    from sqlalchemy import text

    with storage.engine.connect() as connection:
        connection.execute(text(acquire), params)
        connection.commit()
        try:
            yield
        finally:
            connection.execute(text(release), params)
            connection.commit()


@contextlib.contextmanager
def heartbeat(study_storage: StudyStorage, trial_id: int) -> Iterator[None]:
    """Record the trial's heartbeat every interval while the block runs (no-op without heartbeat support)."""
    storage, interval = study_storage.storage, study_storage.heartbeat_interval
    if interval is None or not isinstance(storage, RDBStorage):
        yield
        return
    stop = threading.Event()

    def beat() -> None:
        while True:
            try:
                storage.record_heartbeat(trial_id)
            except Exception as err:  # noqa: BLE001  (a database hiccup must not kill the trial; the next beat may succeed)
                logger.warning("heartbeat of trial id %d failed: %s", trial_id, err)
            if stop.wait(interval):
                return

    thread = threading.Thread(target=beat, name=f"heartbeat-{trial_id}", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()

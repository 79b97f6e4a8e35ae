"""Episode records in one SQLite file per run: ``<runs_dir>/<run>/results.sqlite``.

Each (run, episode) is stored exactly once: a second submission of the same episode (a retry
after a lost ack, a re-leased episode) is recognised and ignored, so N episodes give N rows.
"""

from __future__ import annotations

import sqlite3
from datetime import UTC, datetime
from pathlib import Path

from agos.runtime import keys
from agos.runtime.codec import from_json, to_json
from agos.runtime.schemas import EpisodeRecord

SCHEMA = """
CREATE TABLE IF NOT EXISTS episodes (
    run_id      TEXT NOT NULL,
    episode_id  TEXT NOT NULL,
    difficulty  TEXT NOT NULL,
    status      TEXT NOT NULL,
    success     INTEGER NOT NULL,
    record_json TEXT NOT NULL,
    stored_utc  TEXT NOT NULL,
    PRIMARY KEY (run_id, episode_id)
);
"""


class ResultStore:
    """The records of one run's ``results.sqlite`` (``create=False``: read only); a context manager
    that closes the file."""

    def __init__(self, path: Path, *, create: bool = True) -> None:
        if create:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(path)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.executescript(SCHEMA)
        else:
            self._db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        self.path = path

    def add(self, record: EpisodeRecord) -> bool:
        """Store a record once per (run, episode); return False when nothing changed.

        A ``finished`` record replaces an infrastructure-failure record of the same episode (a resumed
        run re-plays episodes that failed for reasons outside the agents); nothing ever replaces a
        ``finished`` record, and a repeated submission is ignored."""
        row = (record.run_id, record.episode_id, record.difficulty, record.status, int(record.success),
               to_json(record).decode(), datetime.now(UTC).isoformat(timespec="seconds"))
        with self._db:
            cur = self._db.execute("INSERT OR IGNORE INTO episodes VALUES (?, ?, ?, ?, ?, ?, ?)", row)
            if cur.rowcount == 0 and record.status == "finished":
                cur = self._db.execute(
                    "UPDATE episodes SET difficulty = ?, status = ?, success = ?, record_json = ?, stored_utc = ? "
                    "WHERE run_id = ? AND episode_id = ? AND status != 'finished'", (*row[2:], *row[:2]))
        return cur.rowcount == 1

    def finished_ids(self) -> set[str]:
        """Episodes with a ``finished`` record (what ``agos eval --resume`` does not run again)."""
        return {r[0] for r in self._db.execute("SELECT episode_id FROM episodes WHERE status = 'finished'")}

    def records(self, run_id: str | None = None) -> list[EpisodeRecord]:
        sql = "SELECT record_json FROM episodes" + (" WHERE run_id = ?" if run_id else "") + " ORDER BY episode_id"
        rows = self._db.execute(sql, (run_id,) if run_id else ())
        return [from_json(r[0], EpisodeRecord) for r in rows]

    def raw_records(self) -> list[tuple[str, str]]:
        """(episode id, record JSON) of every stored episode, in episode order."""
        return list(self._db.execute("SELECT episode_id, record_json FROM episodes ORDER BY run_id, episode_id"))

    def close(self) -> None:
        """Close the database; a second call does nothing."""
        self._db.close()

    def __enter__(self) -> ResultStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def results_path(runs_dir: Path, run_id: str) -> Path:
    """``<runs_dir>/<run_id>/results.sqlite``; a run id that is not a name (``..``, ``a/b``) raises
    ``ValueError``: no file is ever made outside the runs directory."""
    return runs_dir / keys.check_chunk(run_id, what="run id") / "results.sqlite"

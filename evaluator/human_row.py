"""Which runs are the Human reference: the paper's main table puts the Human row first.

A run is the Human reference when a person played both roles (policy ``human``, ``agos human``).
Its policies are read from the run directory's ``run.json`` (a run directory, or the
``results.sqlite`` inside one); where there is none (a copied results file, a JSONL of records),
from the decision traces of its first record, which name the policy that made each decision
(agents/human/board.py writes ``policy: human``).
"""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path
from typing import Any

HUMAN = "human"
LABEL = "Human"


def run_policies(path: Path) -> dict[str, str]:
    """Role -> policy name of the run at ``path`` ({} when nothing says)."""
    run_json = path / "run.json" if path.is_dir() else path.parent / "run.json"
    if run_json.exists():
        try:
            policies = json.loads(run_json.read_text()).get("policies")
        except (OSError, json.JSONDecodeError):
            policies = None
        if isinstance(policies, dict):
            return {str(k): str(v) for k, v in policies.items()}
    record = _first_record(path / "results.sqlite" if path.is_dir() else path)
    traces = record.get("decision_traces") if isinstance(record, dict) else None
    out: dict[str, str] = {}
    for trace in traces if isinstance(traces, list) else []:
        if isinstance(trace, dict) and isinstance(trace.get("role"), str) and isinstance(trace.get("policy"), str):
            out.setdefault(trace["role"], trace["policy"])
    return out


def is_human_run(path: Path) -> bool:
    """A person played both roles of the run at ``path``."""
    policies = run_policies(path)
    return len(policies) == 2 and all(p.partition(":")[0] == HUMAN for p in policies.values())


def _first_record(path: Path) -> Any:
    try:
        if path.suffix in (".sqlite", ".db"):
            db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
            try:
                row = db.execute("SELECT record_json FROM episodes WHERE status = 'finished' LIMIT 1").fetchone()
            finally:
                db.close()
            return json.loads(row[0]) if row else None
        with path.open() as f:
            return json.loads(next((line for line in f if line.strip()), "null"))
    except (OSError, sqlite3.Error, json.JSONDecodeError, UnicodeDecodeError):
        return None  # not readable as records: read_run says why, with the file and line

"""The ledger of scheduled recalibration: which campaign inputs are calibrated, and who is
calibrating one right now. Science only (no Prefect). SYNOPSIS::

    from tasks.campaign.recalibration_ledger import Ledger
    ledger = Ledger.under(results_root)                # <results>/.recalibration/
    if not ledger.is_done(campaign_id, input_sha256):
        with ledger.claim(campaign_id) as mine:
            if mine and not ledger.is_done(campaign_id, input_sha256):   # re-check under the claim
                ...calibrate...
                ledger.mark_done(campaign_id, input_sha256, {"report": ...})

Layout::

    <results>/.recalibration/
      locks/<campaign_id>.lock                 flock'ed while a run calibrates the campaign
      done/<campaign_id>/<input_sha256>.json   written (atomically) once its calibration completed

**Exactly once.** A done record exists only after a calibration completed; it is written by a
temporary file and a rename, so it is whole or absent. The claim is an exclusive, non-blocking
``flock`` on the campaign's lock file: a second run (another schedule tick, another process) that
finds it held skips the campaign, and the kernel releases it when its holder ends for any reason,
so a run killed mid-calibration leaves no done record and no stale lock: the next tick retries.
Only a crash between the end of the calibration and the rename of the done record repeats a
calibration (its stages then come from Prefect's cache and the lake partitions are replaced
whole). ``flock`` is reliable between processes of one host on a local file system; on a network
file system give every host its own results root or run one server.
"""

from __future__ import annotations

import fcntl
import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path

from tasks.core.atomic_io import atomic_write_text
from tasks.lake.store import check_name, results_root

LEDGER_DIR = ".recalibration"


class Ledger:
    """The recalibration ledger in ``folder`` (created on first use)."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)

    @classmethod
    def under(cls, root: str | Path | None = None) -> Ledger:
        """The ledger of the results lake ``root`` (see :func:`tasks.lake.store.results_root`)."""
        return cls(results_root(root) / LEDGER_DIR)

    def _done_path(self, campaign_id: str, input_sha256: str) -> Path:
        check_name("campaign_id", campaign_id)
        if len(input_sha256) != 64 or any(c not in "0123456789abcdef" for c in input_sha256):
            raise ValueError(f"input_sha256 must be 64 lower-case hex digits, not {input_sha256!r}")
        return self.folder / "done" / campaign_id / f"{input_sha256}.json"

    def is_done(self, campaign_id: str, input_sha256: str) -> bool:
        """True once :meth:`mark_done` has recorded this campaign input."""
        return self._done_path(campaign_id, input_sha256).is_file()

    def mark_done(self, campaign_id: str, input_sha256: str, record: dict) -> Path:
        """Record the completed calibration of this input (JSON ``record`` plus campaign_id,
        input_sha256 and finished_utc), atomically. Returns the record's path."""
        path = self._done_path(campaign_id, input_sha256)
        doc = {"campaign_id": campaign_id, "input_sha256": input_sha256,
               "finished_utc": datetime.now(UTC).isoformat(timespec="seconds"), **record}
        atomic_write_text(path, json.dumps(doc, indent=1, default=str))
        return path

    def record(self, campaign_id: str, input_sha256: str) -> dict | None:
        """The done record of this campaign input (None when not done)."""
        path = self._done_path(campaign_id, input_sha256)
        return json.loads(path.read_text()) if path.is_file() else None

    def records(self) -> list[dict]:
        """Every done record, sorted by finish time then campaign_id."""
        docs = [json.loads(p.read_text()) for p in self.folder.glob("done/*/*.json")]
        return sorted(docs, key=lambda d: (d.get("finished_utc", ""), d.get("campaign_id", "")))

    @contextmanager
    def claim(self, campaign_id: str) -> Iterator[bool]:
        """Hold the campaign's lock for the ``with`` block: yields True when this caller holds it,
        False when another run does (then do nothing). Never blocks."""
        check_name("campaign_id", campaign_id)
        path = self.folder / "locks" / f"{campaign_id}.lock"
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                yield False
                return
            try:
                os.ftruncate(fd, 0)
                os.write(fd, json.dumps({"pid": os.getpid(), "since_utc": datetime.now(UTC).isoformat()}).encode())
                yield True
            finally:
                fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)

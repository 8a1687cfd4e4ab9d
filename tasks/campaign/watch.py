"""Find the campaign folders dropped into a watched directory, and which are ready to calibrate.

Science only (no Prefect). SYNOPSIS::

    from tasks.campaign.watch import scan_watch_dir
    found, skipped = scan_watch_dir(Path("/lab/campaigns"))
    for entry in found:   entry.campaign_id, entry.folder, entry.input_sha256, entry.quiet_s
    for s in skipped:     s.folder, s.reason          # logged, retried next scan

A **campaign folder** is a folder holding ``campaign.json`` or ``manifest.csv``; the scan looks
for them at any depth below the watched directory (so a lab may file campaigns by year or week),
does not descend into a campaign folder (its ``captures/`` hold the verification captures, which
are campaign folders too) and skips hidden folders (names starting with ``.``: the place to copy a
campaign before renaming it into view).

A campaign is **identified** by its ``campaign_id`` and the sha256 of its ``campaign.json`` and
``manifest.csv`` bytes (``input_sha256``): the same campaign re-dropped is the same input; a new
manifest is a new input. A folder is **skipped** (with the reason) when either file is missing,
when :func:`tasks.campaign.ingest.load_campaign_metadata` or :func:`tasks.campaign.ingest.load_manifest` rejects
it, or when two folders carry the same campaign_id with different content. Whether a folder is
still being copied is judged by the caller from ``quiet_s``: seconds since anything in it (other
than ``captures/``) last changed, by the later of each file's modification and status-change
time (a copy that preserves modification times still sets the status-change time).
"""

from __future__ import annotations

import hashlib
import os
import time
from dataclasses import dataclass
from pathlib import Path

from tasks.campaign.capture_request import has_capture
from tasks.campaign.folder import MANIFEST_FILE, METADATA_FILE
from tasks.campaign.ingest import CampaignError, load_campaign_metadata, load_manifest

OUTPUT_DIRS = frozenset({"captures"})  # written into a campaign folder by the calibration itself


@dataclass(frozen=True)
class CampaignEntry:
    """A readable campaign folder: its id, absolute path, input hash (hex sha256), seconds since
    its last change, and how many manifest images are missing (ingest records them as faults)."""

    campaign_id: str
    folder: str
    input_sha256: str
    quiet_s: float
    missing_images: int


@dataclass(frozen=True)
class Skipped:
    """A folder that is not (yet) a usable campaign, and why."""

    folder: str
    reason: str


def campaign_folders(watch_dir: Path) -> list[Path]:
    """Every non-hidden folder below ``watch_dir`` holding campaign.json or manifest.csv, sorted;
    campaign folders are not descended into. Raises FileNotFoundError if ``watch_dir`` is not a folder."""
    watch_dir = Path(watch_dir)
    if not watch_dir.is_dir():
        raise FileNotFoundError(f"watched directory {watch_dir} does not exist or is not a folder")
    found = []
    for root, dirs, files in os.walk(watch_dir):
        if METADATA_FILE in files or MANIFEST_FILE in files:
            found.append(Path(root))
            dirs[:] = []
        else:
            dirs[:] = sorted(d for d in dirs if not d.startswith("."))
    return sorted(found)


def input_sha256(folder: Path) -> str:
    """sha256 (hex) of campaign.json and manifest.csv, each length-prefixed."""
    h = hashlib.sha256()
    for name in (METADATA_FILE, MANIFEST_FILE):
        data = (Path(folder) / name).read_bytes()
        h.update(f"{name}:{len(data)}:".encode())
        h.update(data)
    return h.hexdigest()


def seconds_since_change(folder: Path, now: float | None = None) -> float:
    """Seconds from the latest modification or status change of any file or folder in ``folder``
    (the folder itself included, ``captures/`` excluded) to ``now`` (default: the clock)."""
    latest = 0.0
    for root, dirs, files in os.walk(folder):
        if Path(root) == Path(folder):
            dirs[:] = [d for d in dirs if d not in OUTPUT_DIRS]
        for name in [".", *files]:
            try:
                st = os.stat(os.path.join(root, name), follow_symlinks=False)
            except FileNotFoundError:  # removed while we looked: it changed just now
                return 0.0
            latest = max(latest, st.st_mtime, st.st_ctime)
    return max(0.0, (time.time() if now is None else now) - latest)


def capture_arrived(record: dict | None, settle_seconds: float, now: float | None = None) -> bool:
    """Whether a campaign calibrated while its verification capture was only requested (done
    record ``capture_state`` "requested", ``capture`` its folder) has the lab's capture now: the
    folder holds manifest.csv and nothing in it changed for ``settle_seconds``."""
    if not record or record.get("capture_state") != "requested" or not record.get("capture"):
        return False
    folder = Path(record["capture"])
    return has_capture(folder) and seconds_since_change(folder, now) >= settle_seconds


def read_entry(folder: Path, now: float | None = None) -> CampaignEntry:
    """The :class:`CampaignEntry` of ``folder``; raises :class:`tasks.campaign.ingest.CampaignError`
    (message naming the file) when it is incomplete or malformed."""
    folder = Path(folder).absolute()
    for name in (METADATA_FILE, MANIFEST_FILE):
        if not (folder / name).is_file():
            raise CampaignError(f"{folder / name}: missing (campaign incomplete or still being copied)")
    metadata = load_campaign_metadata(folder)
    manifest = load_manifest(folder)
    missing = sum(not (folder / p).is_file() for p in manifest["path"] if p)
    return CampaignEntry(str(metadata["campaign_id"]), str(folder), input_sha256(folder),
                         seconds_since_change(folder, now), int(missing))


def scan_watch_dir(watch_dir: Path, now: float | None = None) -> tuple[list[CampaignEntry], list[Skipped]]:
    """The readable campaigns below ``watch_dir`` (one per campaign_id and content) and the
    skipped folders with their reasons. Two folders with the same campaign_id and content: the
    first (sorted by path) is kept, the other skipped as a copy; with different content: both
    skipped (which one is the campaign is the lab's call)."""
    entries, skipped = [], []
    for folder in campaign_folders(watch_dir):
        try:
            entries.append(read_entry(folder, now))
        except (CampaignError, OSError) as e:
            skipped.append(Skipped(str(folder), str(e)))
    by_id: dict[str, list[CampaignEntry]] = {}
    for e in entries:
        by_id.setdefault(e.campaign_id, []).append(e)
    kept = []
    for campaign_id, group in by_id.items():
        if len({e.input_sha256 for e in group}) > 1:
            folders = ", ".join(e.folder for e in group)
            skipped += [Skipped(e.folder, f"campaign_id {campaign_id!r} is in several folders with different "
                                          f"content ({folders}): rename one") for e in group]
            continue
        kept.append(group[0])
        skipped += [Skipped(e.folder, f"a copy of {group[0].folder} (same campaign_id and content)")
                    for e in group[1:]]
    return sorted(kept, key=lambda e: e.folder), skipped

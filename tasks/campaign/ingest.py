"""Ingest: check a campaign folder against its contract and build the ``images`` table.

SYNOPSIS::

    from tasks.campaign.ingest import check_campaign, summarise, format_summary
    metadata, images = check_campaign("data/campaigns/demo")
    print(format_summary(summarise(images)))
    images.loc[images.status != "ok", ["image_id", "status", "message"]]

Two levels of fault, as design §7 asks:

- **campaign level** — no folder, no or unreadable ``campaign.json`` or one that breaks its schema
  (``tasks.campaign.schema``: the key at fault is named), no, unreadable, too large or empty
  ``manifest.csv``, a required manifest column missing, or a campaign that is mostly faults: no
  usable image, or more than :data:`MAX_FAULT_FRACTION` of its rows faulty
  (:func:`check_usable`). :class:`CampaignError` names the file; nothing is written.
- **image level** — one row of the ``images`` table per manifest row, with a ``status`` (``"ok"``
  or a short code of :data:`STATUS_CODES`) and a ``message`` that names the manifest row and the
  file. A faulty row does not stop the others; downstream stages use the rows with status ok.

The work is split so that each part can be cached and vectorised:

- :func:`check_manifest`: every check that needs only the manifest and ``campaign.json``
  (camera names, axis values against the strokes, timestamps, duplicated image ids), vectorised
  over rows with pandas.
- :func:`check_image_files`: reads, hashes (sha256 of the bytes) and decodes the files of one
  chunk of rows, one image in memory at a time. Its result depends only on the chunk's manifest
  row numbers, paths and file bytes (and :data:`CODE_VERSION`), which is what
  :func:`chunk_content_key` hashes, so a pipeline can cache it by content.
- :func:`build_images_table`: joins both, checks size and bit depth against the camera, finds
  duplicated content across the whole campaign, and writes one status and message per row.

Manifest rows are numbered from 1: row n is the n-th data record after the header (blank lines
skipped), so row 1 is the second line of a plain manifest.csv. No stage reads ``truth/``.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import re
import stat
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from tasks.campaign.folder import MANIFEST_COLUMNS, MANIFEST_FILE, MANIFEST_STAGES, METADATA_FILE
from tasks.campaign.schema import SUPPORTED_FORMAT_VERSIONS, SchemaFault, check_metadata
from tasks.machine.description import COMMAND_COLUMNS

CODE_VERSION = "ingest-2"  # bump when check_image_files would return something else for the same bytes
CHUNK_SIZE = 32  # images per cached chunk
# Size limits of the files a campaign holds (bytes): a full-size 8-bit image is 6.3 MB raw, a
# manifest about 150 bytes a row, so these leave a wide margin and stop a runaway file early.
MAX_IMAGE_BYTES = 64 * 2**20
MAX_METADATA_BYTES = 16 * 2**20
MAX_MANIFEST_BYTES = 256 * 2**20
# A campaign with more faulty rows than this fraction (or no usable image) is a campaign fault:
# it is refused whole rather than replacing a good partition with a table of faults.
MAX_FAULT_FRACTION = 0.5
# A timestamp later than the ingest time by more than this is a fault (a clock error).
FUTURE_TOLERANCE = pd.Timedelta(days=1)
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# the first bytes of other formats OpenCV decodes, to name what a misnamed file is
OTHER_FORMATS = ((b"\xff\xd8\xff", "JPEG"), (b"BM", "BMP"), (b"II*\x00", "TIFF"), (b"MM\x00*", "TIFF"),
                 (b"RIFF", "WebP"), (b"\x00\x00\x00\x0cjP", "JPEG 2000"), (b"P5", "PGM"), (b"P6", "PPM"))
OPTIONAL_COLUMNS = ("temperature_c",)
REQUIRED_COLUMNS = tuple(c for c in MANIFEST_COLUMNS if c not in OPTIONAL_COLUMNS)
AXIS_UNITS = {"X_mm": "mm", "Y_mm": "mm", "Z_mm": "mm", "A_deg": "deg", "C_deg": "deg"}
STROKE_TOLERANCE = 1e-6  # mm or deg; manifest values are written with 6 decimals
CAMPAIGN_ID_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")

# Status codes in priority order: a row with several faults gets the first as its status and
# all of them in its message.
STATUS_CODES: dict[str, str] = {
    "malformed_row": "the manifest row has more or fewer fields than the header; its values are not used",
    "bad_path": "the path is empty, absolute or leaves the campaign folder (also after following links)",
    "missing_file": "no file at the path (or the path is a folder)",
    "unreadable_file": "the file cannot be read (permissions, I/O error), is not a regular file (a device, "
                       "a pipe) or is larger than MAX_IMAGE_BYTES",
    "corrupt_image": "the file is empty, truncated or not a decodable image",
    "wrong_format": "the file is an image but not a PNG (by its content, whatever its name says)",
    "wrong_bit_depth": "the image is not 8-bit single-channel (e.g. RGB, 16-bit)",
    "wrong_size": "width × height differ from the camera's in campaign.json",
    "duplicate_image": "same file content as an earlier row, or an image_id used by an earlier row",
    "unknown_camera": "the camera is not in campaign.json cameras",
    "bad_stage": "the stage is not one of MANIFEST_STAGES, or the group does not fit the stage",
    "nan_axis": "an axis command is missing, not a number or not finite",
    "out_of_stroke": "an axis command is outside the axis' stroke in campaign.json (often a unit error)",
    "bad_timestamp": "the timestamp is missing, not an ISO 8601 time or in the future",
    "out_of_order": "the timestamp breaks capture order (rows are in capture order; the longest ordered run "
                    "of rows leaves this one out)",
    "bad_value": "another field is invalid: empty image_id, non-integer repeat, non-numeric temperature",
}
PRIORITY = {code: i for i, code in enumerate(STATUS_CODES)}

# The images table, column by column (the partition column campaign_id is first here and stored
# by the results lake as the hive partition, not inside the file).
IMAGES_COLUMNS = (
    "campaign_id", "manifest_row", "image_id", "path", "camera", "stage", "group", "repeat",
    "X_mm", "Y_mm", "Z_mm", "A_deg", "C_deg", "timestamp", "temperature_c",
    "content_sha256", "width_px", "height_px", "status", "message",
)
FILE_FACT_COLUMNS = ("manifest_row", "content_sha256", "width_px", "height_px", "channels", "dtype",
                     "file_fault", "file_detail")


class CampaignError(Exception):
    """A campaign-level fault: the campaign cannot be ingested at all. The message names the file."""


# ---------------------------------------------------------------------------------------------
# campaign level


class FileFault(Exception):
    """A campaign file that cannot be read safely: ``code`` is a status code of
    :data:`STATUS_CODES` (bad_path, missing_file, unreadable_file), ``detail`` says why in words."""

    def __init__(self, code: str, detail: str):
        super().__init__(detail)
        self.code, self.detail = code, detail


def read_campaign_file(folder: str | Path, relpath: str | Path, limit: int) -> bytes:
    """The bytes of the file ``relpath`` of the campaign folder ``folder``, read safely.

    The path is resolved after following every link and must stay inside the (resolved) folder
    (else ``bad_path``); the file must exist (``missing_file``), be a regular file, not a folder,
    device, pipe or socket, and hold at most ``limit`` bytes (``unreadable_file``). It is opened
    without blocking, so a pipe or device never hangs the reader. Raises :class:`FileFault`.
    """
    root = os.path.realpath(folder)
    target = os.path.realpath(os.path.join(root, relpath))
    if target != root and not target.startswith(root.rstrip(os.sep) + os.sep):
        raise FileFault("bad_path", f"path leads outside the campaign folder (to {target}) after following links")
    try:
        fd = os.open(target, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC | getattr(os, "O_NOFOLLOW", 0))
    except FileNotFoundError:
        raise FileFault("missing_file", "file missing") from None
    except OSError as e:
        raise FileFault("unreadable_file", f"cannot read file ({e.strerror})") from None
    try:
        info = os.fstat(fd)
        if stat.S_ISDIR(info.st_mode):
            raise FileFault("missing_file", "is a folder, not a file")
        if not stat.S_ISREG(info.st_mode):
            raise FileFault("unreadable_file", "not a regular file (a device, pipe or socket): not read")
        if info.st_size > limit:
            raise FileFault("unreadable_file", f"file too large ({info.st_size} bytes, the limit is {limit})")
        blocks, size = [], 0
        while block := os.read(fd, 1 << 20):
            blocks.append(block)
            size += len(block)
            if size > limit:  # grew while being read
                raise FileFault("unreadable_file", f"file too large (over {limit} bytes)")
        return b"".join(blocks)
    except OSError as e:
        raise FileFault("unreadable_file", f"cannot read file ({e.strerror})") from None
    finally:
        os.close(fd)


def load_campaign_metadata(folder: str | Path) -> dict:
    """Read and validate ``<folder>/campaign.json``.

    Checked: the folder exists; the file exists, is a regular file of at most
    :data:`MAX_METADATA_BYTES` inside the folder, UTF-8 JSON holding an object; a supported
    ``format_version``; a ``campaign_id`` usable as a folder name (letters, digits, ``._-``); then
    the schema of ``tasks.campaign.schema`` (cameras, plates, views, machine: types and ranges,
    e.g. a pitch ≤ 0 is named by its key). Returns the parsed metadata unchanged. Raises
    :class:`CampaignError` naming the file and the key at fault.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise CampaignError(f"{folder}: campaign folder does not exist or is not a folder")
    path = folder / METADATA_FILE
    try:
        text = read_campaign_file(folder, METADATA_FILE, MAX_METADATA_BYTES).decode("utf-8")
    except FileFault as e:
        if e.code == "missing_file":
            raise CampaignError(f"{path}: campaign metadata file missing") from None
        raise CampaignError(f"{path}: cannot read campaign metadata ({e.detail})") from None
    except UnicodeDecodeError as e:
        raise CampaignError(f"{path}: cannot read campaign metadata ({e})") from e
    try:
        meta = json.loads(text)
    except json.JSONDecodeError as e:
        raise CampaignError(f"{path}: not valid JSON ({e.msg} at line {e.lineno}, column {e.colno})") from e
    except RecursionError:
        raise CampaignError(f"{path}: not valid JSON (nested too deeply)") from None
    if not isinstance(meta, dict):
        raise CampaignError(f"{path}: must hold a JSON object, not {type(meta).__name__}")
    version = meta.get("format_version")
    if not _is_int(version) or version not in SUPPORTED_FORMAT_VERSIONS:
        raise CampaignError(f"{path}: format_version {version!r} is not supported "
                            f"(supported: {', '.join(map(str, SUPPORTED_FORMAT_VERSIONS))})")
    cid = meta.get("campaign_id")
    if not isinstance(cid, str) or not CAMPAIGN_ID_PATTERN.match(cid):
        raise CampaignError(f"{path}: campaign_id {cid!r} must be 1-128 letters, digits, '.', '_' or '-', "
                            "not starting with '.'")
    try:
        check_metadata(meta)
    except SchemaFault as e:
        raise CampaignError(f"{path}: {e}") from None
    return meta


def camera_sizes(metadata: dict) -> dict[str, tuple[int, int]]:
    """{camera: (width_px, height_px)} from validated campaign metadata."""
    return {name: (int(c["width_px"]), int(c["height_px"])) for name, c in metadata["cameras"].items()}


def axis_strokes(metadata: dict) -> dict[str, tuple[float, float]]:
    """{manifest column: (low, high)} stroke limits, mm for X/Y/Z and deg for A/C."""
    axes = metadata["machine"]["axes"]
    return {col: (float(axes[col.split("_")[0]]["stroke"][0]), float(axes[col.split("_")[0]]["stroke"][1]))
            for col in COMMAND_COLUMNS}


def load_manifest(folder: str | Path) -> pd.DataFrame:
    """Read ``<folder>/manifest.csv`` as text, one row per data record.

    Returns a DataFrame with ``manifest_row`` (int, from 1), every column of
    :data:`tasks.campaign.folder.MANIFEST_COLUMNS` as stripped strings (``temperature_c`` is optional
    and "" when absent; extra columns are ignored) and ``malformed`` ("" or why the row's field
    count differs from the header's — such a row is kept, padded or cut to the header, and
    flagged by :func:`check_manifest`). Raises :class:`CampaignError` naming the file when it is
    missing, unreadable, larger than :data:`MAX_MANIFEST_BYTES`, not CSV, lacks a required column,
    has no data row, or has more than :data:`MAX_FAULT_FRACTION` of its rows of the wrong width.
    """
    path = Path(folder) / MANIFEST_FILE
    try:
        text = read_campaign_file(folder, MANIFEST_FILE, MAX_MANIFEST_BYTES).decode("utf-8-sig")
    except FileFault as e:
        raise CampaignError(f"{path}: {'manifest missing' if e.code == 'missing_file' else e.detail}") from None
    except UnicodeDecodeError as e:
        raise CampaignError(f"{path}: cannot read manifest ({e})") from e
    records: list[list[str]] = []
    lines: list[int] = []
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        header = next(reader, None)
        for fields in reader:
            if not fields or all(not s.strip() for s in fields):
                continue  # blank line
            records.append(fields)
            lines.append(reader.line_num)
    except csv.Error as e:
        raise CampaignError(f"{path}: not a readable CSV file (line {reader.line_num}: {e})") from e
    del text
    if header is None:
        raise CampaignError(f"{path}: empty file, no header row")
    header = [h.strip() for h in header]
    dupes = sorted({h for h in header if header.count(h) > 1})
    if dupes:
        raise CampaignError(f"{path}: duplicated column(s) {', '.join(dupes)} in the header")
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise CampaignError(f"{path}: required column(s) {', '.join(missing)} missing from the header "
                            f"(expected {', '.join(MANIFEST_COLUMNS)})")
    if not records:
        raise CampaignError(f"{path}: no image rows (empty campaign)")

    width = len(header)
    n_fields = np.array([len(r) for r in records])
    n_malformed = int((n_fields != width).sum())
    if n_malformed > MAX_FAULT_FRACTION * len(records):  # not a manifest: stop before typing every row
        first = lines[int(np.argmax(n_fields != width))]
        raise CampaignError(f"{path}: {n_malformed} of {len(records)} rows have more or fewer fields than the header's "
                            f"{width}, more than the {MAX_FAULT_FRACTION:.0%} a campaign may have "
                            f"(MAX_FAULT_FRACTION): refused whole, nothing written. First: line {first}")
    padded = [r[:width] + [""] * (width - len(r)) if len(r) != width else r for r in records]
    raw = pd.DataFrame(padded, columns=header, dtype=str)
    out = pd.DataFrame({"manifest_row": np.arange(1, len(records) + 1, dtype=np.int64)})
    for col in MANIFEST_COLUMNS:
        out[col] = raw[col].str.strip().to_numpy() if col in raw.columns else ""
    line = pd.Series(lines, dtype=str)
    out["malformed"] = np.where(
        n_fields != width,
        pd.Series(n_fields.astype(str)) + f" fields where the header has {width} (line " + line + ")",
        "")
    return out


# ---------------------------------------------------------------------------------------------
# manifest checks (vectorised)


def check_manifest(manifest: pd.DataFrame, metadata: dict) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Type the manifest and check every row against ``campaign.json``, vectorised.

    manifest: from :func:`load_manifest`. Returns ``(typed, faults)``, both indexed like the
    manifest. ``typed``: manifest_row, image_id, path, camera, stage, group (str), repeat (Int64),
    X_mm/Y_mm/Z_mm (float, mm), A_deg/C_deg (float, deg), timestamp (UTC), temperature_c (float,
    °C). ``faults``: one str column per check named ``<status code>[:<what>]``, "" where the row
    passes, else a short description (without the row prefix).
    """
    m = manifest
    idx = m.index
    faults: dict[str, pd.Series] = {}
    typed = m[["manifest_row", "image_id", "path", "camera", "stage", "group"]].copy()

    faults["malformed_row"] = m["malformed"].where(m["malformed"] == "", "malformed row: " + m["malformed"])

    path = m["path"]
    absolute = path.str.match(r"^(/|\\|[A-Za-z]:)")
    parent = path.str.contains(r"(?:^|[/\\])\.\.(?:[/\\]|$)")
    faults["bad_path"] = pd.Series(
        np.select([path == "", absolute | parent], ["path empty", "path " + path + " is absolute or leaves the "
                                                    "campaign folder"], ""), index=idx)

    dup_id = m["image_id"].ne("") & m["image_id"].duplicated(keep="first")
    first_row = m.groupby("image_id", sort=False)["manifest_row"].transform("first").astype(str)
    faults["duplicate_image:image_id"] = pd.Series(
        np.where(dup_id, "image_id " + m["image_id"] + " already used by manifest row " + first_row, ""), index=idx)

    cameras = list(metadata["cameras"])
    faults["unknown_camera"] = pd.Series(
        np.where(m["camera"].isin(cameras), "",
                 "camera '" + m["camera"] + f"' not in campaign.json cameras ({', '.join(cameras)})"), index=idx)

    faults["bad_stage"] = _stage_faults(m["stage"], m["group"])

    nan_detail = pd.Series("", index=idx)
    stroke_detail = pd.Series("", index=idx)
    for col, (lo, hi) in axis_strokes(metadata).items():
        raw = m[col]
        value = pd.to_numeric(raw, errors="coerce").astype(float)
        typed[col] = value
        finite = np.isfinite(value.to_numpy())
        nan_msg = np.where(raw == "", f"{col} missing", f"{col} is not a finite number ('" + raw + "')")
        nan_detail = _join(nan_detail, pd.Series(np.where(finite, "", nan_msg), index=idx))
        outside = finite & ((value < lo - STROKE_TOLERANCE) | (value > hi + STROKE_TOLERANCE)).to_numpy()
        msg = f"{col} = " + raw + f" out of stroke [{lo:g}, {hi:g}] {AXIS_UNITS[col]}"
        stroke_detail = _join(stroke_detail, pd.Series(np.where(outside, msg, ""), index=idx))
    faults["nan_axis"] = nan_detail
    faults["out_of_stroke"] = stroke_detail

    stamp = pd.to_datetime(m["timestamp"], utc=True, format="ISO8601", errors="coerce")
    typed["timestamp"] = stamp
    future = (stamp > pd.Timestamp.now(tz="UTC") + FUTURE_TOLERANCE).fillna(False).to_numpy(bool)
    faults["bad_timestamp"] = pd.Series(
        np.select([m["timestamp"] == "", stamp.isna(), future],
                  ["timestamp missing", "timestamp '" + m["timestamp"] + "' is not an ISO 8601 time",
                   "timestamp '" + m["timestamp"] + "' is in the future (a clock error?)"], ""), index=idx)
    faults["out_of_order"] = _order_faults(stamp.where(~future), m["manifest_row"], m["timestamp"])

    repeat = pd.to_numeric(m["repeat"], errors="coerce")
    repeat_ok = np.isfinite(repeat.to_numpy(dtype=float, na_value=np.nan)) & (repeat == np.round(repeat)).to_numpy()
    typed["repeat"] = repeat.where(repeat_ok).astype("Int64")
    temperature = pd.to_numeric(m["temperature_c"], errors="coerce").astype(float)
    typed["temperature_c"] = temperature
    bad_temp = (m["temperature_c"] != "") & ~np.isfinite(temperature.to_numpy())
    faults["bad_value"] = _join(
        _join(pd.Series(np.where(m["image_id"] == "", "image_id empty", ""), index=idx),
              pd.Series(np.where(repeat_ok, "", "repeat '" + m["repeat"] + "' is not an integer"), index=idx)),
        pd.Series(np.where(bad_temp, "temperature_c '" + m["temperature_c"] + "' is not a number", ""), index=idx))

    typed = typed[["manifest_row", "image_id", "path", "camera", "stage", "group", "repeat",
                   *COMMAND_COLUMNS, "timestamp", "temperature_c"]]
    return typed, pd.DataFrame(faults, index=idx)


def _stage_faults(stage: pd.Series, group: pd.Series) -> pd.Series:
    """Per row "" or why ``stage``/``group`` break the vocabulary of MANIFEST_STAGES (vectorised)."""
    known = stage.isin(list(MANIFEST_STAGES))
    group_ok = group != ""
    expected = {}
    for name, rule in MANIFEST_STAGES.items():
        sel = stage == name
        if rule is None:
            group_ok &= ~sel | (group == name)
            expected[name] = f"'{name}'"
        elif rule == "any":
            expected[name] = "a non-empty name"
        else:
            group_ok &= ~sel | group.isin(list(rule))
            expected[name] = "one of " + ", ".join(rule)
    return pd.Series(np.select(
        [~known.to_numpy(), ~group_ok.to_numpy()],
        ["stage '" + stage + f"' is not one of {', '.join(MANIFEST_STAGES)}",
         "group '" + group + "' does not fit stage " + stage + " (expected " + stage.map(expected).fillna("")
         + ")"], ""), index=stage.index)


def _order_faults(stamp: pd.Series, manifest_row: pd.Series, text: pd.Series) -> pd.Series:
    """Per row "" or why its timestamp breaks capture order.

    The rows in order are the longest run of rows whose timestamps never decrease (a longest
    non-decreasing subsequence, O(n log n)); every other row with a time is out of order, named
    against its nearest in-order neighbour. Rows without a time (NaT) are left to bad_timestamp.
    """
    out = np.full(len(stamp), "", dtype=object)
    has = np.flatnonzero(stamp.notna().to_numpy())
    if len(has) < 2:
        return pd.Series(out, index=stamp.index, dtype=object)
    t = stamp.iloc[has].astype("int64").to_numpy()
    kept = has[_longest_non_decreasing(t)]
    out_of_order = np.setdiff1d(has, kept)
    rows, texts, ns = manifest_row.to_numpy(), text.to_numpy(), stamp.astype("int64").to_numpy()
    for i in out_of_order:
        k = np.searchsorted(kept, i)
        if k > 0 and ns[i] < ns[kept[k - 1]]:
            j, rel = kept[k - 1], "earlier than"
        else:
            j, rel = kept[min(k, len(kept) - 1)], "later than"
        out[i] = (f"timestamp '{texts[i]}' is {rel} manifest row {rows[j]}'s ('{texts[j]}'): rows must be in "
                  "capture order")
    return pd.Series(out, index=stamp.index, dtype=object)


def _longest_non_decreasing(values: np.ndarray) -> np.ndarray:
    """Indices of one longest non-decreasing subsequence of ``values`` (patience sorting)."""
    import bisect

    tails: list[int] = []      # tails[k]: smallest last value of a run of length k+1
    tail_idx: list[int] = []   # its index
    prev = np.full(len(values), -1)
    for i, v in enumerate(values.tolist()):
        k = bisect.bisect_right(tails, v)
        if k == len(tails):
            tails.append(v)
            tail_idx.append(i)
        else:
            tails[k], tail_idx[k] = v, i
        prev[i] = tail_idx[k - 1] if k > 0 else -1
    out, i = [], tail_idx[-1]
    while i >= 0:
        out.append(i)
        i = prev[i]
    return np.array(out[::-1], dtype=np.int64)


def _join(a: pd.Series, b: pd.Series, sep: str = "; ") -> pd.Series:
    """Element-wise ``a + sep + b``, leaving out the separator where either side is empty."""
    return a + pd.Series(np.where((a != "") & (b != ""), sep, ""), index=a.index) + b


# ---------------------------------------------------------------------------------------------
# per-file checks (chunked)


def image_chunks(manifest: pd.DataFrame, faults: pd.DataFrame, chunk_size: int = CHUNK_SIZE) -> list[pd.DataFrame]:
    """The rows whose files are to be read, as chunks of ``[manifest_row, path]`` in manifest order.

    Rows that are malformed or have a bad path are not read. Chunks are consecutive manifest rows,
    so a chunk's content (and its cache key) changes only when one of its own rows or files does.
    """
    readable = (faults["malformed_row"] == "") & (faults["bad_path"] == "")
    rows = manifest.loc[readable, ["manifest_row", "path"]].reset_index(drop=True)
    return [rows.iloc[i:i + chunk_size].reset_index(drop=True) for i in range(0, len(rows), chunk_size)]


def file_sha256(path: str | Path) -> str:
    """sha256 (hex) of a file's bytes, read in blocks (memory does not grow with the file). For files
    the caller knows to be regular; campaign files go through :func:`read_campaign_file`."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _file_token(folder: Path, relpath: str) -> str:
    """The content of a campaign file for a cache key: its sha256, or the fault that stops reading it
    (read as :func:`read_campaign_file` reads it: inside the folder, regular files, size-limited)."""
    try:
        return hashlib.sha256(read_campaign_file(folder, relpath, MAX_IMAGE_BYTES)).hexdigest()
    except FileFault as e:
        return f"{e.code}:{e.detail}"


def chunk_content_key(folder: str | Path, rows: pd.DataFrame) -> str:
    """Key of :func:`check_image_files` (folder, rows): everything its result depends on.

    That is: :data:`CODE_VERSION`, the OpenCV version (it decodes), and for each row its manifest
    row number, its path and the sha256 of its file's bytes (or the :class:`FileFault` that stops
    reading it).
    Not the folder's location, so a copied campaign hits the same key; not mtimes, so touching a file
    does not invalidate it. Every file is read to hash it — cheap next to decoding.
    """
    folder = Path(folder)
    items = [[int(r), str(p), _file_token(folder, p)] for r, p in zip(rows["manifest_row"], rows["path"], strict=True)]
    doc = json.dumps({"code": CODE_VERSION, "opencv": cv2.__version__, "rows": items}, separators=(",", ":"))
    return hashlib.sha256(doc.encode()).hexdigest()


def inspect_image_file(folder: str | Path, relpath: str) -> dict[str, Any]:
    """Read (:func:`read_campaign_file`), hash and decode one image file of a campaign folder
    (``cv2.IMREAD_UNCHANGED``: no conversion).

    Returns content_sha256 (hex of the bytes, None when unreadable), width_px, height_px,
    channels, dtype (None when not decoded), file_fault ("" or bad_path / missing_file /
    unreadable_file / corrupt_image / wrong_format) and file_detail (the problem in words).
    """
    facts: dict[str, Any] = {"content_sha256": None, "width_px": None, "height_px": None, "channels": None,
                             "dtype": None, "file_fault": "", "file_detail": ""}
    try:
        data = read_campaign_file(folder, relpath, MAX_IMAGE_BYTES)
    except FileFault as e:
        return {**facts, "file_fault": e.code, "file_detail": e.detail}
    facts["content_sha256"] = hashlib.sha256(data).hexdigest()
    if not data:
        return {**facts, "file_fault": "corrupt_image", "file_detail": "file is empty (0 bytes)"}
    try:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        image = None
    if image is None or image.size == 0:
        return {**facts, "file_fault": "corrupt_image",
                "file_detail": f"cannot be decoded as an image (corrupt or truncated, {len(data)} bytes)"}
    facts.update(width_px=int(image.shape[1]), height_px=int(image.shape[0]),
                 channels=1 if image.ndim == 2 else int(image.shape[2]), dtype=str(image.dtype))
    if not data.startswith(PNG_SIGNATURE):
        kind = next((name for magic, name in OTHER_FORMATS if data.startswith(magic)), "another format")
        return {**facts, "file_fault": "wrong_format",
                "file_detail": f"not a PNG: the content is {kind} (the format is read from the bytes, not the name)"}
    return facts


def check_image_files(folder: str | Path, rows: pd.DataFrame) -> pd.DataFrame:
    """:func:`inspect_image_file` for each row of a chunk; one decoded image in memory at a time.

    rows: ``[manifest_row, path]`` (paths relative to ``folder``). Returns :data:`FILE_FACT_COLUMNS`,
    one row per input row. Depends only on what :func:`chunk_content_key` hashes.
    """
    facts = [{"manifest_row": int(r), **inspect_image_file(folder, p)}
             for r, p in zip(rows["manifest_row"], rows["path"], strict=True)]
    return _facts_frame(facts)


def _facts_frame(facts: list[dict]) -> pd.DataFrame:
    df = pd.DataFrame(facts, columns=list(FILE_FACT_COLUMNS))
    df["manifest_row"] = df["manifest_row"].astype(np.int64)
    for col in ("width_px", "height_px", "channels"):
        df[col] = df[col].astype("Int64")
    for col in ("content_sha256", "dtype"):
        df[col] = df[col].astype("str").where(df[col].notna(), None) if len(df) else df[col].astype(object)
    return df


# ---------------------------------------------------------------------------------------------
# the images table


def build_images_table(campaign_id: str, typed: pd.DataFrame, faults: pd.DataFrame,
                       file_facts: pd.DataFrame | list[pd.DataFrame], metadata: dict) -> pd.DataFrame:
    """Join manifest and file checks into the ``images`` table (:data:`IMAGES_COLUMNS`).

    typed, faults: from :func:`check_manifest`. file_facts: the :func:`check_image_files` results
    of all chunks (any order). Adds the checks that need both, vectorised: bit depth (8-bit
    single-channel), size (the camera's width_px × height_px) and duplicated content (the same
    sha256 as an earlier manifest row; the later row is flagged). status is the first fault in
    :data:`STATUS_CODES` order, message lists all of them after "manifest row n (path): ".
    A malformed row reports only that it is malformed.
    """
    if isinstance(file_facts, list):
        file_facts = pd.concat(file_facts, ignore_index=True) if file_facts else _facts_frame([])
    facts = typed[["manifest_row"]].merge(file_facts, on="manifest_row", how="left", validate="one_to_one")
    facts.index = typed.index
    idx = typed.index
    faults = faults.copy()
    for code in ("bad_path", "missing_file", "unreadable_file", "corrupt_image", "wrong_format"):
        faults[f"{code}:file"] = facts["file_detail"].where(facts["file_fault"] == code, "").fillna("")

    decoded = facts["dtype"].notna() & (facts["file_fault"] != "wrong_format")
    depth_ok = (facts["dtype"] == "uint8") & (facts["channels"] == 1)
    bad_depth = decoded & ~depth_ok.fillna(False).astype(bool)
    faults["wrong_bit_depth:file"] = pd.Series(
        np.where(bad_depth, "expected 8-bit single-channel, got " + facts["dtype"].fillna("").astype(str) + " with "
                 + facts["channels"].astype(str) + " channel(s)", ""), index=idx)

    sizes = camera_sizes(metadata)
    exp_w = typed["camera"].map({k: v[0] for k, v in sizes.items()}).astype("Int64")
    exp_h = typed["camera"].map({k: v[1] for k, v in sizes.items()}).astype("Int64")
    wrong = (decoded & exp_w.notna() & ((facts["width_px"] != exp_w) | (facts["height_px"] != exp_h))
             ).fillna(False).astype(bool)
    faults["wrong_size:file"] = pd.Series(
        np.where(wrong, "size " + facts["width_px"].astype(str) + "x" + facts["height_px"].astype(str) + " px, "
                 + typed["camera"] + " expects " + exp_w.astype(str) + "x" + exp_h.astype(str) + " px", ""),
        index=idx)

    sha = facts["content_sha256"]
    has_sha = sha.notna()
    dup = has_sha & sha.duplicated(keep="first")
    first = typed["manifest_row"].groupby(sha).transform("first")
    first_id = typed["image_id"].groupby(sha).transform("first")
    faults["duplicate_image:content"] = pd.Series(
        np.where(dup, "same content as manifest row " + first.astype("Int64").astype(str) + " (" + first_id.fillna("")
                 + ")", ""), index=idx)

    # malformed rows: their fields are not trustworthy, report only that
    malformed = faults["malformed_row"] != ""
    faults.loc[malformed, [c for c in faults.columns if c != "malformed_row"]] = ""

    order = sorted(faults.columns, key=lambda c: PRIORITY[c.split(":")[0]])
    faults = faults[order]
    has = faults.ne("").to_numpy()  # (N, K)
    any_fault = has.any(axis=1)
    codes = np.array([c.split(":")[0] for c in order])
    status = np.where(any_fault, codes[has.argmax(axis=1)], "ok")
    detail = pd.Series("", index=idx)
    for col in order:
        detail = _join(detail, faults[col])
    shown = typed["path"].where(typed["path"] != "", "no path")
    message = np.where(any_fault, "manifest row " + typed["manifest_row"].astype(str) + " (" + shown + "): " + detail,
                       "")

    images = typed.copy()
    images.insert(0, "campaign_id", campaign_id)
    images["manifest_row"] = images["manifest_row"].astype("Int64")
    images["content_sha256"] = sha
    images["width_px"] = facts["width_px"].astype("Int64")
    images["height_px"] = facts["height_px"].astype("Int64")
    images["status"] = pd.Series(status, index=idx, dtype=str)
    images["message"] = pd.Series(message, index=idx, dtype=str)
    return images[list(IMAGES_COLUMNS)].reset_index(drop=True)


def campaign_content_hash(folder: str | Path, images: pd.DataFrame) -> str:
    """sha256 identifying the ingested input: campaign.json and manifest.csv bytes, then every
    image's content hash in manifest order ("-" where the file could not be read)."""
    h = hashlib.sha256()
    for name, limit in ((METADATA_FILE, MAX_METADATA_BYTES), (MANIFEST_FILE, MAX_MANIFEST_BYTES)):
        h.update(f"{name}:{hashlib.sha256(read_campaign_file(folder, name, limit)).hexdigest()}\n".encode())
    for sha in images["content_sha256"].fillna("-"):
        h.update(f"{sha}\n".encode())
    return h.hexdigest()


def summarise(images: pd.DataFrame) -> dict[str, Any]:
    """Counts of the images table: n_images, n_ok, n_faults and {status: count} (ok first)."""
    counts = images["status"].value_counts()
    by_status = {code: int(counts[code]) for code in ("ok", *STATUS_CODES) if code in counts.index}
    n_ok = by_status.get("ok", 0)
    return {"campaign_id": str(images["campaign_id"].iloc[0]) if len(images) else None,
            "n_images": len(images), "n_ok": n_ok, "n_faults": len(images) - n_ok, "by_status": by_status}


def format_summary(summary: dict[str, Any]) -> str:
    """One line for a person: 'campaign c: 124 images, 120 ok, 4 faults (missing_file 1, ...)'."""
    faults = ", ".join(f"{k} {v}" for k, v in summary["by_status"].items() if k != "ok")
    text = f"campaign {summary['campaign_id']}: {summary['n_images']} images, {summary['n_ok']} ok, " \
           f"{summary['n_faults']} faults"
    return text + (f" ({faults})" if faults else "")


def _first_fault(faults: pd.DataFrame, manifest_row: pd.Series) -> str:
    """'manifest row n: <every fault of the first faulty row>'."""
    bad = faults.ne("")
    i = int(np.flatnonzero(bad.any(axis=1).to_numpy())[0])
    return f"manifest row {manifest_row.iloc[i]}: " + "; ".join(v for v in faults.iloc[i] if v)


def _refuse_mostly_faults(where: Path, n_faulty: int, n_rows: int, what: str, example: str) -> None:
    if n_faulty > MAX_FAULT_FRACTION * n_rows:
        raise CampaignError(f"{where}: {n_faulty} of {n_rows} rows are faulty {what}, more than the "
                            f"{MAX_FAULT_FRACTION:.0%} a campaign may have (MAX_FAULT_FRACTION): refused whole, "
                            f"nothing written. First: {example}")


def read_checked_manifest(folder: str | Path) -> tuple[dict, pd.DataFrame, pd.DataFrame]:
    """Every check that needs no image: ``(metadata, typed, faults)`` of :func:`check_manifest`.

    Raises :class:`CampaignError` on a campaign-level fault, including a manifest whose rows are
    faulty by the manifest alone in more than :data:`MAX_FAULT_FRACTION` of them (e.g. a valid
    header followed by garbage), before any image is read.
    """
    metadata = load_campaign_metadata(folder)
    typed, faults = check_manifest(load_manifest(folder), metadata)
    faulty = faults.ne("").any(axis=1)
    if faulty.any():
        _refuse_mostly_faults(Path(folder) / MANIFEST_FILE, int(faulty.sum()), len(faults), "by the manifest alone",
                              _first_fault(faults, typed["manifest_row"]))
    return metadata, typed, faults


def check_usable(folder: str | Path, images: pd.DataFrame) -> None:
    """Raise :class:`CampaignError` when the images table makes an unusable campaign: no row with
    status ok, or more than :data:`MAX_FAULT_FRACTION` of the rows faulty."""
    summary = summarise(images)
    if summary["n_ok"] == 0:
        raise CampaignError(f"{folder}: no usable image ({format_summary(summary)}): refused whole, nothing "
                            f"written. First: {images['message'].iloc[0]}")
    if summary["n_faults"]:
        first = images.loc[images["status"] != "ok", "message"].iloc[0]
        _refuse_mostly_faults(Path(folder), summary["n_faults"], summary["n_images"],
                              f"({format_summary(summary)})", first)


def check_campaign(folder: str | Path, chunk_size: int = CHUNK_SIZE) -> tuple[dict, pd.DataFrame]:
    """All checks of one campaign without Prefect and without writing: ``(metadata, images)``.

    The same steps as the ingest flow, run sequentially and uncached. Raises
    :class:`CampaignError` on a campaign-level fault (:func:`read_checked_manifest`,
    :func:`check_usable`).
    """
    metadata, typed, faults = read_checked_manifest(folder)
    facts = [check_image_files(folder, rows) for rows in image_chunks(typed, faults, chunk_size)]
    images = build_images_table(metadata["campaign_id"], typed, faults, facts, metadata)
    check_usable(folder, images)
    return metadata, images


def ingest_provenance(folder: str | Path, images: pd.DataFrame) -> dict[str, Any]:
    """Provenance stored with the images table: fivecal version, input hash, parameters."""
    from tasks.core.version import FIVECAL_VERSION

    return {"fivecal_version": FIVECAL_VERSION, "input_sha256": campaign_content_hash(folder, images),
            "parameters": {"code_version": CODE_VERSION, "opencv": cv2.__version__,
                           "stroke_tolerance": STROKE_TOLERANCE}}


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


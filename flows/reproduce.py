"""Reproduce a calibration report (``fivecal reproduce REPORT_DIR``).

SYNOPSIS::

    from flows.reproduce import reproduce_report
    code = reproduce_report(Path("reports/demo/20261121T101500Z"))   # prints; 0 = every number reproduced

1. Load what the report recorded (``REPORT_DIR/data/``, tasks/report/data.py): its tables, the
   per-image content hashes, the parameters (campaign folder, detector, fivecal version, ...).
2. Check that the campaign's inputs still hash the same: campaign.json, manifest.csv and every
   image; say which changed, went missing or appeared.
3. Re-run ``flows.calibrate.calibrate_campaign`` with the recorded parameters into a temporary
   results root and reports root, with Prefect's cache refreshed (every task runs again; a
   reproduction that read the cache would prove nothing).
4. Compare every number of every recorded table with the reproduction's: rows matched by the
   table's keys (tasks/lake/schema.py); integers, text and flags exactly; floats to a relative
   tolerance of 1e-9; NaN equals NaN. Timings (columns marked not reproducible) are not compared.

The re-run uses the recorded OpenCV thread count. OpenCV's multi-threaded camera calibration
differs from call to call by about 1e-6 px, which the identification amplifies to relative
differences of 1e-4 and more; the measure flow therefore calibrates and estimates poses with one
OpenCV/BLAS thread (tasks.steps.vision.one_numeric_thread, since commit 70a1d86). Reports made
before that may not reproduce.

Exit codes of the command: 0 every number reproduced, 1 inputs changed or numbers differ, 2 the
report or its campaign cannot be read.
"""

from __future__ import annotations

import contextlib
import json
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from tasks.core.version import FIVECAL_VERSION, code_fingerprint
from tasks.lake.schema import PARTITION, TABLES
from tasks.report.data import (
    DATA_DIR,
    INPUTS_FILE,
    PARAMETERS_FILE,
    REPORT_TABLES,
    campaign_file_hashes,
    environment,
)

REL_TOL = 1e-9
RUN_NAME = "reproduction"
MAX_PRINTED = 50  # differences printed per table


class ReproduceError(Exception):
    """The report or its campaign cannot be used; the message names the file."""


@dataclass
class Recorded:
    """What a report folder recorded: parameters.json, its tables and (if recorded) the input hashes."""

    folder: Path
    parameters: dict[str, Any]
    tables: dict[str, pd.DataFrame]
    inputs: pd.DataFrame | None

    @property
    def campaign(self) -> Path:
        return Path(self.parameters["provenance"]["campaign"])

    @property
    def detector(self) -> str:
        return str(self.parameters["provenance"].get("detector", "rrht"))

    @property
    def calibrate_options(self) -> dict[str, Any]:
        """The recorded run's model and compensation options, as calibrate_campaign's keywords."""
        p = self.parameters["provenance"]
        return {"effects": list(p.get("effects", [])), "effect_modules": list(p.get("effect_modules", [])),
                "orientation": str(p.get("orientation_objective", "full")),
                "verification_repeats": int(p.get("verification_repeats", 1))}


@dataclass
class Difference:
    table: str
    key: str          # "name=delta_AZ" (the table's keys) or "row 3"
    column: str       # "(row)" for a missing or extra row, a column name otherwise
    recorded: Any
    reproduced: Any


@dataclass
class Comparison:
    numbers: int = 0                  # numeric cells compared
    texts: int = 0                    # text and flag cells compared
    differences: list[Difference] = field(default_factory=list)
    not_compared: list[str] = field(default_factory=list)  # "formulations.total_300_ms (timing)"
    notes: list[str] = field(default_factory=list)

    def add(self, other: Comparison) -> None:
        self.numbers += other.numbers
        self.texts += other.texts
        self.differences += other.differences
        self.not_compared += other.not_compared
        self.notes += other.notes


def load_report(report_dir: str | Path) -> Recorded:
    """The recorded data of ``report_dir``; ReproduceError if it has no data/parameters.json."""
    folder = Path(report_dir)
    data = folder / DATA_DIR
    params_file = data / PARAMETERS_FILE
    if not params_file.is_file():
        raise ReproduceError(f"{params_file}: missing — {folder} is not a report folder, or was written by a "
                             "fivecal that did not record its numbers; run fivecal calibrate again")
    try:
        parameters = json.loads(params_file.read_text(encoding="utf-8"))
    except ValueError as e:
        raise ReproduceError(f"{params_file}: not valid JSON ({e})") from None
    if not isinstance(parameters, dict) or "campaign" not in (parameters.get("provenance") or {}):
        raise ReproduceError(f"{params_file}: no provenance.campaign (the campaign folder) recorded")
    tables = {name: pd.read_parquet(data / f"{name}.parquet") for name in REPORT_TABLES
              if (data / f"{name}.parquet").is_file()}
    inputs = pd.read_parquet(data / INPUTS_FILE) if (data / INPUTS_FILE).is_file() else None
    return Recorded(folder, parameters, tables, inputs)


# --------------------------------------------------------------------------------------------
# Inputs
# --------------------------------------------------------------------------------------------


def input_changes(recorded: Recorded, campaign: Path | None = None) -> list[str]:
    """What differs between the recorded inputs and the campaign folder (``campaign``, else the
    recorded one): one line per changed, missing or new file; [] when everything hashes the same.
    Without recorded per-image hashes only campaign.json and manifest.csv are checked (and the
    images' combined hash after the re-run, see :func:`compare_reports`)."""
    from tasks.campaign.ingest import file_sha256

    folder = Path(campaign) if campaign is not None else recorded.campaign
    if not folder.is_dir():
        return [f"{folder}: the campaign folder is missing"]
    changes = []
    now = campaign_file_hashes(folder)
    for name, sha in recorded.parameters.get("campaign_files_sha256", {}).items():
        if sha is not None and now.get(name) != sha:
            changes.append(f"{folder / name}: " + ("missing" if now.get(name) is None else
                                                   f"content changed (sha256 {sha[:12]}… → {now[name][:12]}…)"))
    if recorded.inputs is None:
        return changes
    for r in recorded.inputs.itertuples(index=False):
        path = folder / str(r.path)
        if pd.isna(r.content_sha256):
            continue  # unreadable when the report was made: not an input of it
        try:
            sha = file_sha256(path)
        except OSError:
            changes.append(f"{path} (manifest row {r.manifest_row}): missing or unreadable")
            continue
        if sha != r.content_sha256:
            changes.append(f"{path} (manifest row {r.manifest_row}): content changed "
                           f"(sha256 {r.content_sha256[:12]}… → {sha[:12]}…)")
    return changes


# --------------------------------------------------------------------------------------------
# Re-run
# --------------------------------------------------------------------------------------------


@contextlib.contextmanager
def opencv_threads(n: int | None) -> Iterator[None]:
    """OpenCV's thread count set to ``n`` for the block (None: unchanged), restored afterwards.
    Process-wide: OpenCV calls of other threads see it too."""
    import cv2

    before = cv2.getNumThreads()
    if n is not None:
        cv2.setNumThreads(int(n))
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def rerun(recorded: Recorded, workdir: Path, campaign: Path | None = None) -> tuple[Path, dict[str, Any]]:
    """Calibrate the campaign again with the recorded detector, model and compensation options
    (:attr:`Recorded.calibrate_options`) and OpenCV thread count into ``workdir/results`` and
    ``workdir/reports``, every Prefect task run afresh
    (PREFECT_TASKS_REFRESH_CACHE). Returns (the reproduced report folder, calibrate's summary).
    Note: a simulated campaign's verification capture is rendered again into ``<campaign>/captures/``."""
    from prefect.settings import PREFECT_TASKS_REFRESH_CACHE, temporary_settings

    from flows.calibrate import calibrate_campaign

    folder = Path(campaign) if campaign is not None else recorded.campaign
    threads = recorded.parameters.get("environment", {}).get("opencv_threads")
    with temporary_settings(updates={PREFECT_TASKS_REFRESH_CACHE: True}), opencv_threads(threads):
        summary = calibrate_campaign(str(folder), results_root=str(workdir / "results"), detector=recorded.detector,
                                     reports_root=str(workdir / "reports"), run=RUN_NAME,
                                     **recorded.calibrate_options)
    if cached := cached_steps(summary.get("cached", {})):
        raise ReproduceError(f"the re-run read Prefect's cache ({', '.join(cached)}): it would prove nothing")
    return Path(summary["markdown"]).parent, summary


def cached_steps(cached: dict[str, Any], prefix: str = "") -> list[str]:
    """The steps a calibrate summary's ``cached`` entry reports as served from the cache: flags that
    are True and counts above 0, nested dicts (a subflow's counts) included, as "measure.detect"."""
    out = []
    for key, value in cached.items():
        if isinstance(value, dict):
            out += cached_steps(value, f"{prefix}{key}.")
        elif value is True or (isinstance(value, int | float) and not isinstance(value, bool) and value > 0):
            out.append(f"{prefix}{key}")
    return out


# --------------------------------------------------------------------------------------------
# Comparison
# --------------------------------------------------------------------------------------------


def same(a: Any, b: Any) -> bool:
    """Equal as the comparison counts it: NaN/NA equals NaN/NA, floats to REL_TOL, the rest exactly."""
    na_a, na_b = bool(pd.isna(a)), bool(pd.isna(b))
    if na_a or na_b:
        return na_a and na_b
    if isinstance(a, float) or isinstance(b, float):
        return a == b or abs(a - b) <= REL_TOL * max(abs(a), abs(b))
    return a == b


def _keys(name: str, rec: pd.DataFrame, rep: pd.DataFrame) -> list[str]:
    keys = [k for k in TABLES[name].keys if k != PARTITION] if name in TABLES else []
    ok = keys and all(k in rec.columns and k in rep.columns for k in keys)
    return keys if ok and not rec.duplicated(keys).any() and not rep.duplicated(keys).any() else []


def compare_frames(name: str, rec: pd.DataFrame, rep: pd.DataFrame) -> Comparison:
    """Every cell of the recorded frame against the reproduced one (rows matched by the table's keys,
    else by position)."""
    out = Comparison()
    keys = _keys(name, rec, rep)
    if keys:
        r, p = rec.set_index(keys), rep.set_index(keys)
    else:
        out.notes.append(f"{name}: rows matched by position (its keys do not identify a row)")
        r, p = rec.reset_index(drop=True), rep.reset_index(drop=True)

    def label(i) -> str:
        if not keys:
            return f"row {i}"
        return ", ".join(f"{k}={v}" for k, v in zip(keys, i if isinstance(i, tuple) else (i,), strict=True))

    in_p, in_r = set(p.index), set(r.index)
    out.differences += [Difference(name, label(i), "(row)", "present", "missing") for i in r.index if i not in in_p]
    out.differences += [Difference(name, label(i), "(row)", "absent", "present") for i in p.index if i not in in_r]
    common = [i for i in r.index if i in in_p]
    timing = {c.name for c in TABLES[name].columns if not c.reproducible} if name in TABLES else set()
    for col in r.columns:
        if col in timing:
            out.not_compared.append(f"{name}.{col} (timing)")
            continue
        if col not in p.columns:
            out.differences.append(Difference(name, "(every row)", col, "present", "missing"))
            continue
        numeric = pd.api.types.is_numeric_dtype(r[col]) and not pd.api.types.is_bool_dtype(r[col])
        a, b = r.loc[common, col].tolist(), p.loc[common, col].tolist()
        out.differences += [Difference(name, label(i), col, x, y) for i, x, y in zip(common, a, b, strict=True)
                            if not same(x, y)]
        if numeric:
            out.numbers += len(common)
        else:
            out.texts += len(common)
    out.differences += [Difference(name, "(every row)", col, "absent", "present") for col in p.columns
                        if col not in r.columns]
    return out


def compare_reports(recorded: Recorded, reproduced: Recorded) -> Comparison:
    """Every recorded table against the reproduction's, and the images' combined content hash."""
    out = Comparison()
    for name, rec in recorded.tables.items():
        if name not in reproduced.tables:
            out.differences.append(Difference(name, "(table)", "(table)", "present", "missing"))
            continue
        out.add(compare_frames(name, rec, reproduced.tables[name]))
    key = "images_content_sha256"
    a, b = recorded.parameters["provenance"].get(key), reproduced.parameters["provenance"].get(key)
    if a is not None and a != b:
        out.differences.append(Difference("provenance", key, key, a, b))
    return out


def _value(v: Any) -> str:
    return repr(v) if isinstance(v, float) else str(v)


def format_comparison(c: Comparison) -> str:
    """The differences (table, row key, column, recorded vs reproduced), or "all N numbers reproduced"."""
    lines = [*c.notes]
    if c.not_compared:
        lines.append(f"not compared (they differ from run to run): {', '.join(c.not_compared)}")
    if not c.differences:
        lines.append(f"all {c.numbers} numbers reproduced (and {c.texts} text values and flags)")
        return "\n".join(lines)
    by_table: dict[str, list[Difference]] = {}
    for d in c.differences:
        by_table.setdefault(d.table, []).append(d)
    for table, diffs in by_table.items():
        lines.append(f"{table}: {len(diffs)} difference(s)")
        for d in diffs[:MAX_PRINTED]:
            rel = ""
            if isinstance(d.recorded, float) and isinstance(d.reproduced, float) and d.recorded == d.recorded:
                rel = f" (rel. diff {abs(d.recorded - d.reproduced) / max(abs(d.recorded), abs(d.reproduced)):.2g})"
            lines.append(f"  {d.key}  {d.column}: recorded {_value(d.recorded)}, reproduced "
                         f"{_value(d.reproduced)}{rel}")
        if len(diffs) > MAX_PRINTED:
            lines.append(f"  … {len(diffs) - MAX_PRINTED} more")
    lines.append(f"{len(c.differences)} difference(s) among {c.numbers} numbers and {c.texts} text values")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# The whole reproduction
# --------------------------------------------------------------------------------------------


def describe(recorded: Recorded) -> str:
    """One paragraph: what the report is and what it was made with, against what runs now."""
    from tasks.steps.calibration import IDENTIFICATION_CODE_VERSION

    prov = recorded.parameters["provenance"]
    code, now = recorded.parameters.get("code_sha256"), code_fingerprint()
    lines = [f"report {recorded.folder}: campaign {recorded.parameters['campaign_id']} "
             f"({recorded.campaign}), run {recorded.parameters['run']}, detector {recorded.detector}",
             f"recorded with fivecal {prov.get('fivecal_version')} (now {FIVECAL_VERSION}), identification "
             f"code {prov.get('identification_code')} (now {IDENTIFICATION_CODE_VERSION}), code sha256 "
             f"{str(code)[:12]}… (now {now[:12]}…)",
             f"recorded tables: {', '.join(f'{n} ({len(t)} rows)' for n, t in recorded.tables.items())}"]
    env, env_now = recorded.parameters.get("environment", {}), environment()
    moved = [f"{k} {v} (now {env_now.get(k)})" for k, v in env.items() if k != "opencv_threads" and v != env_now.get(k)]
    if moved:
        lines.append(f"environment differs: {', '.join(moved)}")
    if "opencv_threads" in env:
        lines.append(f"OpenCV threads as recorded: {env['opencv_threads']}")
    if (prov.get("fivecal_version"), prov.get("identification_code"), code) != \
            (FIVECAL_VERSION, IDENTIFICATION_CODE_VERSION, now):
        lines.append("note: the code differs from the report's; differences may come from that")
    return "\n".join(lines)


def reproduce_report(report_dir: str | Path, campaign: str | Path | None = None, workdir: str | Path | None = None,
                     echo: Callable[[str], None] = print, error: Callable[[str], None] | None = None) -> int:
    """Check the inputs, re-run and compare, printing through ``echo`` (errors through ``error``,
    default ``echo``); returns the exit code
    (0 reproduced, 1 inputs changed or differences, 2 the report or campaign cannot be used).
    campaign: the campaign folder if it moved (default: the recorded path). workdir: where the
    reproduction's results and report go (default: a temporary folder, removed afterwards)."""
    try:
        recorded = load_report(report_dir)
        echo(describe(recorded))
        folder = Path(campaign) if campaign is not None else recorded.campaign
        changes = input_changes(recorded, folder)
        if changes:
            echo("the campaign's inputs differ from the report's; not re-running:\n  " + "\n  ".join(changes))
            return 1
        n_images = "" if recorded.inputs is None else f" and {recorded.inputs.content_sha256.notna().sum()} images"
        echo(f"inputs: campaign.json, manifest.csv{n_images} hash as recorded")
        with tempfile.TemporaryDirectory(prefix="fivecal-reproduce-") as tmp:
            work = Path(workdir) if workdir is not None else Path(tmp)
            echo(f"re-running calibrate with Prefect's cache refreshed into {work}")
            reproduced_dir, _ = rerun(recorded, work, folder)
            comparison = compare_reports(recorded, load_report(reproduced_dir))
    except ReproduceError as e:
        (error or echo)(f"error: {e}")
        return 2
    echo(format_comparison(comparison))
    threads = recorded.parameters.get("environment", {}).get("opencv_threads", 0)
    if comparison.differences and threads > 1:
        echo(f"note: the report was made with {threads} OpenCV threads; OpenCV's multi-threaded camera "
             "calibration is not bitwise repeatable (about 1e-6 px, amplified by the identification), so a report "
             "made before the measure flow pinned it to one thread may not reproduce")
    return 1 if comparison.differences else 0

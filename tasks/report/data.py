"""The report's numbers in machine-readable form, for ``fivecal reproduce`` (science only, no Prefect).

A report folder holds::

    data/<table>.parquet   pdge, pige, compensation, verification, formulations: the frames the report
                           shows, with the lake table's columns (docs/results-schema.md); each file's
                           ``fivecal`` metadata has table, campaign_id, schema_version
    data/inputs.parquet    the images table's manifest_row, image_id, path, content_sha256, status
                           (when the report was given the images table)
    data/parameters.json   campaign_id, run, simulated, the provenance (campaign folder, detector,
                           fivecal version, input hashes, ...), sha256 of campaign.json and
                           manifest.csv, a fingerprint of the code (``code_sha256``), the
                           environment (library versions, OpenCV's thread count: OpenCV's
                           multi-threaded camera calibration is not bitwise repeatable) and per
                           table its rows and schema version
"""

from __future__ import annotations

import json
import platform
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import pandas as pd

from tasks.campaign.folder import MANIFEST_FILE, METADATA_FILE
from tasks.core.atomic_io import atomic_write_parquet, atomic_write_text
from tasks.core.version import FIVECAL_VERSION, code_fingerprint
from tasks.lake import schema as lake_schema

if TYPE_CHECKING:
    from matplotlib.figure import Figure


@dataclass
class ReportData:
    """Everything one report shows. Frames as in docs/report.md (units in the column names)."""

    campaign_id: str
    run: str                      # run folder name, e.g. "20261121T101500-ab12cd"
    pdge: pd.DataFrame
    pige: pd.DataFrame
    verification: pd.DataFrame
    camera_calibration: pd.DataFrame | None = None
    detector_comparison: pd.DataFrame | None = None
    formulations: pd.DataFrame | None = None
    identifiability: list[str] = field(default_factory=list)
    extra_sections: list[tuple[str, str]] = field(default_factory=list)
    extra_figures: list[tuple[str, Figure]] = field(default_factory=list)
    provenance: dict = field(default_factory=dict)
    simulated: bool = False
    compensation: pd.DataFrame | None = None  # only written to data/ (tasks/report/data.py), not shown
    images: pd.DataFrame | None = None        # the images table: the input hashes in data/inputs.parquet


DATA_DIR = "data"
PARAMETERS_FILE = "parameters.json"
INPUTS_FILE = "inputs.parquet"
REPORT_TABLES = ("pdge", "pige", "compensation", "verification", "formulations")
INPUT_COLUMNS = ("manifest_row", "image_id", "path", "content_sha256", "status")
CAMPAIGN_FILES = (METADATA_FILE, MANIFEST_FILE)
FORMAT_VERSION = 1


def campaign_file_hashes(folder: str | Path | None) -> dict[str, str | None]:
    """{file name: sha256 hex, or None if unreadable} of campaign.json and manifest.csv in ``folder``."""
    from tasks.campaign.ingest import file_sha256

    out: dict[str, str | None] = {}
    for name in CAMPAIGN_FILES:
        try:
            out[name] = file_sha256(Path(folder) / name) if folder else None
        except OSError:
            out[name] = None
    return out


def environment() -> dict:
    """The libraries and settings the numbers depend on: versions, OpenCV's thread count, CPU arch."""
    import cv2
    import numpy
    import pandas
    import pyarrow
    import scipy

    return {"python": platform.python_version(), "numpy": numpy.__version__, "scipy": scipy.__version__,
            "pandas": pandas.__version__, "pyarrow": pyarrow.__version__, "opencv": cv2.__version__,
            "opencv_threads": cv2.getNumThreads(), "machine": platform.machine(), "system": platform.system()}


def write_report_data(folder: Path, data: ReportData) -> dict[str, Path]:
    """Write ``folder/data/``: one Parquet file per table of :data:`REPORT_TABLES` that ``data``
    carries (units and frames as in the lake), inputs.parquet when ``data.images`` is given, and
    parameters.json. Returns {name: path} of the files written."""

    out = Path(folder) / DATA_DIR
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, Path] = {}
    tables = {}
    for name in REPORT_TABLES:
        df = getattr(data, name)
        if df is None:
            continue
        df = lake_schema.conform(name, df.drop(columns=lake_schema.PARTITION, errors="ignore"))
        meta = {"table": name, "campaign_id": data.campaign_id, "schema_version": lake_schema.schema_version(name)}
        atomic_write_parquet(out / f"{name}.parquet", df, meta)
        written[name] = out / f"{name}.parquet"
        tables[name] = {"rows": len(df), "schema_version": meta["schema_version"]}
    if data.images is not None:
        atomic_write_parquet(out / INPUTS_FILE, data.images[[c for c in INPUT_COLUMNS if c in data.images.columns]],
                             {"campaign_id": data.campaign_id})
        written["inputs"] = out / INPUTS_FILE
    parameters = {"format_version": FORMAT_VERSION, "campaign_id": data.campaign_id, "run": data.run,
                  "simulated": data.simulated, "written_by_fivecal": FIVECAL_VERSION,
                  "provenance": data.provenance,
                  "campaign_files_sha256": campaign_file_hashes(data.provenance.get("campaign")),
                  "code_sha256": code_fingerprint(), "environment": environment(),
                  "tables": tables}
    atomic_write_text(out / PARAMETERS_FILE, json.dumps(parameters, indent=1, sort_keys=True, default=str))
    written["parameters"] = out / PARAMETERS_FILE
    return written

"""Fuzz tests (hypothesis) of the campaign parsers: any campaign.json and any manifest.csv end in a
result or a named campaign fault (CampaignError), never another exception or a hang.

campaign.json: arbitrary JSON documents, and the tiny campaign's valid metadata with one value
replaced by arbitrary JSON or one key deleted (deep in the structure, where the analysis reads).
Metadata that passes must build what the analysis builds from it (the nominal machine and the
plates): the schema promises measure will not crash on it. manifest.csv: arbitrary text, and
CSV rows of arbitrary fields under the valid header; when it passes, the manifest checks return
one row per record. Each example has a deadline, so a hang fails the test. Derandomized (the
suite is deterministic): the same 100 examples per test each run; runs with random examples
and more of them are for development (raise max_examples, drop derandomize).
"""

from __future__ import annotations

import copy
import json
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tasks.campaign.folder import MANIFEST_COLUMNS
from tasks.campaign.ingest import CampaignError, load_campaign_metadata, read_checked_manifest

FUZZ = settings(max_examples=100, deadline=5000, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-10**6, 10**6) | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=12),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4),
    max_leaves=12)


def _paths(value, prefix=()):
    """Every key path of a JSON value (dict keys and list indices)."""
    yield prefix
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _paths(v, (*prefix, k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from _paths(v, (*prefix, i))


@pytest.fixture(scope="module")
def valid_metadata(tiny_campaign) -> dict:
    return json.loads((tiny_campaign / "campaign.json").read_text())


@pytest.fixture(scope="module")
def scratch(tmp_path_factory, tiny_campaign) -> Path:
    """A folder with the tiny campaign's manifest; each example rewrites one of its files."""
    folder = tmp_path_factory.mktemp("fuzz") / "c"
    folder.mkdir()
    shutil.copy(tiny_campaign / "manifest.csv", folder / "manifest.csv")
    shutil.copy(tiny_campaign / "campaign.json", folder / "campaign.json")
    return folder


def _check_metadata_text(folder: Path, text: str | bytes) -> None:
    target = folder / "campaign.json"
    target.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8", "surrogatepass"))
    try:
        meta = load_campaign_metadata(folder)
    except CampaignError as e:
        assert str(e).startswith(str(target)), e
        return
    from tasks.vision.pipeline import campaign_plates, nominal_machine

    campaign_plates(meta)
    nominal_machine(meta)


@FUZZ
@given(doc=json_values)
def test_any_json_document_is_metadata_or_a_named_fault(scratch, doc):
    _check_metadata_text(scratch, json.dumps(doc, allow_nan=True))


@FUZZ
@given(data=st.data(), replacement=json_values, delete=st.booleans())
def test_valid_metadata_with_one_value_changed_is_metadata_or_a_named_fault(scratch, valid_metadata, data,
                                                                             replacement, delete):
    meta = copy.deepcopy(valid_metadata)
    paths = [p for p in _paths(meta) if p]
    path = data.draw(st.sampled_from(paths))
    parent = meta
    for k in path[:-1]:
        parent = parent[k]
    if delete and isinstance(parent, dict):
        del parent[path[-1]]
    else:
        parent[path[-1]] = replacement
    _check_metadata_text(scratch, json.dumps(meta, allow_nan=True))


@FUZZ
@given(raw=st.binary(max_size=300))
def test_any_bytes_as_metadata_are_a_named_fault(scratch, raw):
    _check_metadata_text(scratch, raw)


def _check_manifest_text(folder: Path, tiny_campaign: Path, text: str) -> None:
    shutil.copy(tiny_campaign / "campaign.json", folder / "campaign.json")
    (folder / "manifest.csv").write_text(text, encoding="utf-8", errors="surrogatepass")
    try:
        _, typed, faults = read_checked_manifest(folder)
    except CampaignError as e:
        assert str(e).startswith(str(folder)), e
        return
    assert len(typed) == len(faults) >= 1
    assert typed["manifest_row"].tolist() == list(range(1, len(typed) + 1))


@FUZZ
@given(text=st.text(max_size=400))
def test_any_text_as_manifest_is_rows_or_a_named_fault(scratch, tiny_campaign, text):
    _check_manifest_text(scratch, tiny_campaign, text)


field = st.one_of(st.text(max_size=10), st.sampled_from(["camera1", "camera2", "pdge", "pige", "X", "trial00",
                                                          "validation", "camera_calibration", "0", "1.5", "-1e9",
                                                          "nan", "inf", "2026-01-05T08:00:00Z", "images/a.png",
                                                          "../x.png", "/etc/passwd", ""]))


@settings(FUZZ, max_examples=50)  # each example runs every manifest check: the costliest here
@given(rows=st.lists(st.lists(field, min_size=0, max_size=len(MANIFEST_COLUMNS) + 2), min_size=0, max_size=12))
def test_any_rows_under_the_valid_header_are_rows_or_a_named_fault(scratch, tiny_campaign, rows):
    import csv
    import io

    out = io.StringIO()
    writer = csv.writer(out)
    writer.writerow(MANIFEST_COLUMNS)
    writer.writerows(rows)
    _check_manifest_text(scratch, tiny_campaign, out.getvalue())


def test_the_fuzzed_folder_is_really_exercised(tiny_campaign):
    """The valid inputs pass the same functions the fuzz tests call (so a fault is not all they see)."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        shutil.copy(tiny_campaign / "campaign.json", folder / "campaign.json")
        _check_manifest_text(folder, tiny_campaign, (tiny_campaign / "manifest.csv").read_text())
        _, typed, faults = read_checked_manifest(folder)
        assert len(typed) == 18 and not faults.ne("").any(axis=None)

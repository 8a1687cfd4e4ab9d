"""Tests of ingest (tasks/campaign/ingest.py) and the results lake (tasks/lake/store.py), without Prefect.

Each bad-input test damages a copy of the 18-image tiny campaign (tests/conftest.py) in one way
and checks that exactly the damaged row gets the expected status, a message naming its manifest
row and file, and that every other row stays ok. Campaign-level faults must raise CampaignError
naming the file and write nothing.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from tasks.campaign.ingest import (
    IMAGES_COLUMNS,
    STATUS_CODES,
    CampaignError,
    check_campaign,
    check_image_files,
    chunk_content_key,
    format_summary,
    ingest_provenance,
    load_campaign_metadata,
    load_manifest,
    summarise,
)
from tasks.core import atomic_io
from tasks.lake import store as results_lake
from tasks.lake.store import read_provenance, read_table, write_partition

N_IMAGES = 18  # C sweeps both stroke ends and home: 3 positions where the others have 2


def read_manifest(folder: Path) -> pd.DataFrame:
    return pd.read_csv(folder / "manifest.csv", dtype=str, keep_default_na=False)


def write_manifest(folder: Path, m: pd.DataFrame) -> None:
    (folder / "manifest.csv").write_text(m.to_csv(index=False))


def image_path(folder: Path, row: int) -> tuple[str, Path]:
    """(relative path, absolute path) of 1-based manifest row ``row``."""
    rel = read_manifest(folder)["path"].iloc[row - 1]
    return rel, folder / rel


def only_fault(images: pd.DataFrame, row: int, status: str) -> pd.Series:
    """Assert manifest row ``row`` (1-based) is the only faulty row, with ``status``; return it."""
    assert len(images) == N_IMAGES
    bad = images[images["status"] != "ok"]
    assert bad["manifest_row"].tolist() == [row], bad[["manifest_row", "status", "message"]].to_string()
    r = bad.iloc[0]
    assert r["status"] == status, r["message"]
    assert r["message"].startswith(f"manifest row {row} ({r['path']}): "), r["message"]
    assert (images.loc[images["status"] == "ok", "message"] == "").all()
    return r


def write_png(path: Path, image: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", image)
    assert ok
    path.write_bytes(buf.tobytes())


# --------------------------------------------------------------------------------------------
# a clean campaign


def test_clean_campaign_gives_one_ok_row_per_manifest_row_with_types_and_hashes(tiny_campaign):
    _, images = check_campaign(tiny_campaign)
    assert list(images.columns) == list(IMAGES_COLUMNS)
    assert summarise(images) == {"campaign_id": "tiny", "n_images": N_IMAGES, "n_ok": N_IMAGES, "n_faults": 0,
                                 "by_status": {"ok": N_IMAGES}}
    assert images["manifest_row"].tolist() == list(range(1, N_IMAGES + 1))
    assert str(images["timestamp"].dt.tz) == "UTC"
    assert images["timestamp"].iloc[0] == pd.Timestamp("2026-01-05T08:00:00Z")
    assert (images[["width_px", "height_px"]].to_numpy() == [768, 512]).all()
    manifest = read_manifest(tiny_campaign)
    assert images["image_id"].tolist() == manifest["image_id"].tolist()
    np.testing.assert_allclose(images["A_deg"], manifest["A_deg"].astype(float))
    rel = images["path"].iloc[5]
    assert images["content_sha256"].iloc[5] == hashlib.sha256((tiny_campaign / rel).read_bytes()).hexdigest()
    assert images["repeat"].dtype == "Int64" and images["X_mm"].dtype == np.float64


def test_chunking_does_not_change_the_table(tiny_campaign):
    _, whole = check_campaign(tiny_campaign, chunk_size=100)
    _, chunked = check_campaign(tiny_campaign, chunk_size=3)
    pd.testing.assert_frame_equal(whole, chunked)


# --------------------------------------------------------------------------------------------
# image-level faults: recorded, named, and the rest goes on


def test_truncated_png_is_corrupt_image(campaign_copy):
    c = campaign_copy()
    rel, path = image_path(c, 6)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    _, images = check_campaign(c)
    r = only_fault(images, 6, "corrupt_image")
    assert "cannot be decoded" in r["message"] and rel in r["message"]
    assert r["content_sha256"] == hashlib.sha256(data[: len(data) // 2]).hexdigest()
    assert pd.isna(r["width_px"])


def test_garbage_and_empty_files_are_corrupt_images(campaign_copy):
    c = campaign_copy()
    image_path(c, 2)[1].write_bytes(b"this is not a PNG")
    image_path(c, 9)[1].write_bytes(b"")
    _, images = check_campaign(c)
    bad = images.set_index("manifest_row").loc[[2, 9]]
    assert bad["status"].tolist() == ["corrupt_image", "corrupt_image"]
    assert "file is empty" in bad.loc[9, "message"]
    assert (images["status"] == "ok").sum() == N_IMAGES - 2


def test_missing_file_message_names_row_and_file(campaign_copy):
    c = campaign_copy()
    rel, path = image_path(c, 17)
    path.unlink()
    _, images = check_campaign(c)
    r = only_fault(images, 17, "missing_file")
    assert r["message"] == f"manifest row 17 ({rel}): file missing"
    assert rel == "images/camera1/img00016.png"
    assert pd.isna(r["content_sha256"])


def test_image_of_another_size_is_wrong_size(campaign_copy):
    c = campaign_copy()
    write_png(image_path(c, 3)[1], np.full((480, 640), 128, np.uint8))
    _, images = check_campaign(c)
    r = only_fault(images, 3, "wrong_size")
    assert "size 640x480 px, camera2 expects 768x512 px" in r["message"]
    assert (r["width_px"], r["height_px"]) == (640, 480)


@pytest.mark.parametrize(("image", "got"), [
    (np.full((512, 768, 3), 128, np.uint8), "uint8 with 3 channel(s)"),
    (np.full((512, 768), 30000, np.uint16), "uint16 with 1 channel(s)"),
], ids=["rgb", "16bit"])
def test_rgb_or_16bit_image_is_wrong_bit_depth(campaign_copy, image, got):
    c = campaign_copy()
    write_png(image_path(c, 4)[1], image)
    _, images = check_campaign(c)
    r = only_fault(images, 4, "wrong_bit_depth")
    assert f"expected 8-bit single-channel, got {got}" in r["message"]


def test_duplicated_content_flags_the_later_row(campaign_copy):
    c = campaign_copy()
    (image_path(c, 12)[1]).write_bytes(image_path(c, 5)[1].read_bytes())
    _, images = check_campaign(c, chunk_size=4)  # the two rows fall in different chunks
    r = only_fault(images, 12, "duplicate_image")
    assert "same content as manifest row 5 (img00004)" in r["message"]


def test_duplicated_image_id_flags_the_later_row(campaign_copy):
    c = campaign_copy()
    m = read_manifest(c)
    m.loc[7, "image_id"] = m.loc[1, "image_id"]  # row 8 reuses row 2's id
    write_manifest(c, m)
    _, images = check_campaign(c)
    r = only_fault(images, 8, "duplicate_image")
    assert "image_id img00001 already used by manifest row 2" in r["message"]


def test_unknown_camera(campaign_copy):
    c = campaign_copy()
    m = read_manifest(c)
    m.loc[0, "camera"] = "camera9"
    write_manifest(c, m)
    _, images = check_campaign(c)
    r = only_fault(images, 1, "unknown_camera")
    assert "camera 'camera9' not in campaign.json cameras (camera1, camera2)" in r["message"]


@pytest.mark.parametrize("value", ["", "nan", "abc", "inf"])
def test_missing_or_non_numeric_axis_is_nan_axis(campaign_copy, value):
    c = campaign_copy()
    m = read_manifest(c)
    m.loc[14, "Y_mm"] = value
    write_manifest(c, m)
    _, images = check_campaign(c)
    r = only_fault(images, 15, "nan_axis")
    assert "Y_mm" in r["message"]
    assert np.isnan(r["Y_mm"]) or np.isinf(r["Y_mm"])


def test_out_of_stroke_catches_unit_errors_and_names_the_stroke(campaign_copy):
    c = campaign_copy()
    m = read_manifest(c)
    m.loc[4, "X_mm"] = "-1000.0"  # -1 mm written in micrometres: outside ±300 mm
    m.loc[15, "A_deg"] = "120"  # beyond ±92°
    write_manifest(c, m)
    _, images = check_campaign(c)
    bad = images[images["status"] != "ok"].set_index("manifest_row")
    assert bad["status"].to_dict() == {5: "out_of_stroke", 16: "out_of_stroke"}
    assert "X_mm = -1000.0 out of stroke [-300, 300] mm" in bad.loc[5, "message"]
    assert "A_deg = 120 out of stroke [-92, 92] deg" in bad.loc[16, "message"]


def test_bad_timestamp(campaign_copy):
    c = campaign_copy()
    m = read_manifest(c)
    m.loc[9, "timestamp"] = "yesterday"
    m.loc[10, "timestamp"] = ""
    write_manifest(c, m)
    _, images = check_campaign(c)
    bad = images[images["status"] != "ok"].set_index("manifest_row")
    assert bad["status"].to_dict() == {10: "bad_timestamp", 11: "bad_timestamp"}
    assert "timestamp 'yesterday' is not an ISO 8601 time" in bad.loc[10, "message"]
    assert "timestamp missing" in bad.loc[11, "message"]
    assert pd.isna(bad.loc[10, "timestamp"])


def test_path_leaving_the_campaign_folder_is_not_read(campaign_copy):
    c = campaign_copy()
    m = read_manifest(c)
    m.loc[2, "path"] = "../../etc/passwd"
    write_manifest(c, m)
    _, images = check_campaign(c)
    r = only_fault(images, 3, "bad_path")
    assert pd.isna(r["content_sha256"])


def test_malformed_row_is_recorded_and_the_rest_goes_on(campaign_copy):
    c = campaign_copy()
    lines = (c / "manifest.csv").read_text().splitlines()
    lines[7] += ",surplus"  # manifest row 7 (file line 8)
    (c / "manifest.csv").write_text("\n".join(lines) + "\n")
    _, images = check_campaign(c)
    r = only_fault(images, 7, "malformed_row")
    assert "14 fields where the header has 13 (line 8)" in r["message"]


def test_several_faults_in_one_row_are_all_listed_and_status_is_the_first(campaign_copy):
    c = campaign_copy()
    m = read_manifest(c)
    m.loc[13, ["Z_mm", "temperature_c"]] = ["-5000", "warm"]
    write_manifest(c, m)
    image_path(c, 14)[1].unlink()
    _, images = check_campaign(c)
    r = only_fault(images, 14, "missing_file")
    assert "file missing" in r["message"] and "Z_mm = -5000 out of stroke" in r["message"]
    assert "temperature_c 'warm' is not a number" in r["message"]
    assert list(STATUS_CODES).index("missing_file") < list(STATUS_CODES).index("out_of_stroke")


def test_summary_counts_faults(campaign_copy):
    c = campaign_copy()
    image_path(c, 1)[1].unlink()
    image_path(c, 2)[1].unlink()
    image_path(c, 3)[1].write_bytes(b"x")
    _, images = check_campaign(c)
    s = summarise(images)
    assert s["by_status"] == {"ok": N_IMAGES - 3, "missing_file": 2, "corrupt_image": 1}
    assert s["n_faults"] == 3
    assert format_summary(s) == "campaign tiny: 18 images, 15 ok, 3 faults (missing_file 2, corrupt_image 1)"


# --------------------------------------------------------------------------------------------
# campaign-level faults: stop early, name the file, write nothing


def ingest_sequentially(folder: Path, root: Path) -> Path:
    """What the flow does, without Prefect: check, then write the partition."""
    meta, images = check_campaign(folder)
    return write_partition("images", meta["campaign_id"], images, ingest_provenance(folder, images), root)


def raises_campaign_error(folder: Path, tmp_path: Path, *fragments: str) -> None:
    root = tmp_path / "results"
    with pytest.raises(CampaignError) as info:
        ingest_sequentially(folder, root)
    for text in fragments:
        assert text in str(info.value)
    assert not root.exists()


def test_no_manifest(campaign_copy, tmp_path):
    c = campaign_copy()
    (c / "manifest.csv").unlink()
    raises_campaign_error(c, tmp_path, "manifest.csv", "manifest missing")


def test_no_campaign_folder(tmp_path):
    raises_campaign_error(tmp_path / "nowhere", tmp_path, "nowhere", "does not exist")


@pytest.mark.parametrize(("content", "fragment"), [
    ("{not json", "not valid JSON (Expecting property name enclosed in double quotes at line 1, column 2)"),
    ("[1, 2]", "must hold a JSON object"),
    (b"\xff\xfe\x00", "cannot read"),
])
def test_unreadable_metadata(campaign_copy, tmp_path, content, fragment):
    c = campaign_copy()
    target = c / "campaign.json"
    target.write_bytes(content if isinstance(content, bytes) else content.encode())
    raises_campaign_error(c, tmp_path, str(target), fragment)


def test_metadata_without_strokes_or_camera_sizes(campaign_copy, tmp_path):
    c = campaign_copy()
    meta = json.loads((c / "campaign.json").read_text())
    del meta["machine"]["axes"]["Z"]["stroke"]
    (c / "campaign.json").write_text(json.dumps(meta))
    raises_campaign_error(c, tmp_path, "campaign.json", "machine.axes.Z.stroke")
    meta = json.loads((c / "campaign.json").read_text())
    meta["machine"]["axes"]["Z"]["stroke"] = [-200, 200]
    meta["cameras"]["camera2"]["width_px"] = "768"
    (c / "campaign.json").write_text(json.dumps(meta))
    raises_campaign_error(c, tmp_path, "cameras.camera2.width_px must be a positive integer (got '768')")


def test_empty_campaign(campaign_copy, tmp_path):
    c = campaign_copy()
    header = (c / "manifest.csv").read_text().splitlines()[0]
    (c / "manifest.csv").write_text(header + "\n\n")
    raises_campaign_error(c, tmp_path, "manifest.csv", "no image rows (empty campaign)")
    (c / "manifest.csv").write_text("")
    raises_campaign_error(c, tmp_path, "manifest.csv", "empty file, no header row")


def test_manifest_missing_a_column(campaign_copy, tmp_path):
    c = campaign_copy()
    write_manifest(c, read_manifest(c).drop(columns=["C_deg"]))
    raises_campaign_error(c, tmp_path, str(c / "manifest.csv"), "required column(s) C_deg missing")


def test_temperature_column_is_optional(campaign_copy):
    c = campaign_copy()
    write_manifest(c, read_manifest(c).drop(columns=["temperature_c"]))
    assert load_manifest(c)["temperature_c"].eq("").all()
    _, images = check_campaign(c)
    assert (images["status"] == "ok").all() and images["temperature_c"].isna().all()


def test_metadata_is_returned_unchanged(tiny_campaign):
    assert load_campaign_metadata(tiny_campaign) == json.loads((tiny_campaign / "campaign.json").read_text())


# --------------------------------------------------------------------------------------------
# the content key of a chunk


def test_chunk_key_follows_file_content_not_mtime(campaign_copy):
    c = campaign_copy()
    rows = load_manifest(c)[["manifest_row", "path"]].iloc[:4]
    key = chunk_content_key(c, rows)
    path = c / rows["path"].iloc[2]
    os.utime(path, (1, 1))
    assert chunk_content_key(c, rows) == key
    data = bytearray(path.read_bytes())
    data[-20] ^= 0xFF  # same size, other bytes
    path.write_bytes(bytes(data))
    os.utime(path, (1, 1))
    assert chunk_content_key(c, rows) != key
    path.unlink()
    assert chunk_content_key(c, rows) not in (key, chunk_content_key(c, rows.iloc[:3]))


def test_chunk_key_and_result_do_not_depend_on_where_the_campaign_is(campaign_copy, tiny_campaign):
    c = campaign_copy("elsewhere")
    rows = load_manifest(c)[["manifest_row", "path"]].iloc[5:9].reset_index(drop=True)
    assert chunk_content_key(c, rows) == chunk_content_key(tiny_campaign, rows)
    pd.testing.assert_frame_equal(check_image_files(c, rows), check_image_files(tiny_campaign, rows))


# --------------------------------------------------------------------------------------------
# the results lake


def test_partition_round_trip_keeps_types_provenance_and_stores_campaign_id_once(tiny_campaign, tmp_path):
    root = tmp_path / "results"
    path = ingest_sequentially(tiny_campaign, root)
    assert path == root / "images" / "campaign_id=tiny" / "part-0.parquet"
    assert "campaign_id" not in pq.read_schema(path).names
    _, images = check_campaign(tiny_campaign)
    pd.testing.assert_frame_equal(read_table("images", root), images)
    prov = read_provenance("images", "tiny", root)
    assert prov["table"] == "images" and prov["campaign_id"] == "tiny"
    assert set(prov) >= {"fivecal_version", "input_sha256", "parameters"}
    assert len(prov["input_sha256"]) == 64


def test_duckdb_reads_across_campaigns_and_keeps_numeric_ids_as_strings(tiny_campaign, tmp_path):
    root = tmp_path / "results"
    _, images = check_campaign(tiny_campaign)
    write_partition("images", "tiny", images, {}, root)
    write_partition("images", "20260105", images.iloc[:5].assign(campaign_id="20260105"), {}, root)
    both = read_table("images", root)
    assert both["campaign_id"].value_counts().to_dict() == {"tiny": N_IMAGES, "20260105": 5}
    one = read_table("images", root, campaign_id="20260105")
    assert one["campaign_id"].tolist() == ["20260105"] * 5
    assert one["image_id"].tolist() == images["image_id"].iloc[:5].tolist()
    assert read_table("pige", root).empty


def test_rewrite_replaces_the_whole_partition(tiny_campaign, tmp_path):
    root = tmp_path / "results"
    _, images = check_campaign(tiny_campaign)
    write_partition("images", "tiny", images, {"run": 1}, root)
    stray = root / "images" / "campaign_id=tiny" / "part-1.parquet"  # e.g. left by an older writer
    images.drop(columns="campaign_id").to_parquet(stray)
    write_partition("images", "tiny", images.iloc[:3], {"run": 2}, root)
    assert not stray.exists()
    assert len(read_table("images", root)) == 3
    assert read_provenance("images", "tiny", root)["run"] == 2
    assert list((root / ".staging").iterdir()) == []


def test_failed_write_leaves_the_old_partition_whole(tiny_campaign, tmp_path, monkeypatch):
    root = tmp_path / "results"
    _, images = check_campaign(tiny_campaign)
    write_partition("images", "tiny", images, {"run": 1}, root)
    before = (root / "images" / "campaign_id=tiny" / "part-0.parquet").read_bytes()

    def half_written(path, df, metadata=None):
        Path(path).write_bytes(b"PAR1 half")
        raise OSError("disk full")

    monkeypatch.setattr(results_lake, "atomic_write_parquet", half_written)
    with pytest.raises(OSError, match="disk full"):
        write_partition("images", "tiny", images.iloc[:3], {"run": 2}, root)
    assert (root / "images" / "campaign_id=tiny" / "part-0.parquet").read_bytes() == before
    assert list((root / ".staging").iterdir()) == []
    assert len(read_table("images", root)) == N_IMAGES


def test_two_rename_fallback_also_replaces_the_partition(tiny_campaign, tmp_path, monkeypatch):
    root = tmp_path / "results"
    _, images = check_campaign(tiny_campaign)
    write_partition("images", "tiny", images, {}, root)
    monkeypatch.setattr(atomic_io, "_exchange", lambda a, b: False)
    write_partition("images", "tiny", images.iloc[:2], {}, root)
    assert len(read_table("images", root)) == 2
    assert list((root / ".staging").iterdir()) == []


def test_results_root_from_environment(tiny_campaign, tmp_path, monkeypatch):
    monkeypatch.setenv("FIVECAL_RESULTS_DIR", str(tmp_path / "env-lake"))
    _, images = check_campaign(tiny_campaign)
    path = write_partition("images", "tiny", images, {})
    assert path.is_relative_to(tmp_path / "env-lake")
    assert len(read_table("images")) == N_IMAGES


def test_partition_refuses_rows_of_another_campaign(tiny_campaign, tmp_path):
    _, images = check_campaign(tiny_campaign)
    with pytest.raises(ValueError, match="other"):
        write_partition("images", "tiny", images.assign(campaign_id="other"), {}, tmp_path)
    with pytest.raises(ValueError, match="campaign_id"):
        write_partition("images", "../x", images, {}, tmp_path)

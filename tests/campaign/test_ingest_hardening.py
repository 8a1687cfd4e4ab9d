"""Ingest against hostile or careless input (issue 36), without Prefect: what a campaign states is
validated before anything is written, files are read only inside the campaign folder, only regular
files of bounded size, and nothing hangs on a device or a pipe.

Each test damages a copy of the 18-image tiny campaign (tests/conftest.py). Row faults are checked
with check_campaign; campaign faults through the CLI too, which refuses them before any Prefect
server starts, with exit 2 and the previous partition byte for byte as it was.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
from pathlib import Path

import cv2
import pandas as pd
import pytest
from typer.testing import CliRunner

from fivecal.cli import app
from tasks.campaign import ingest
from tasks.campaign.ingest import (
    CampaignError,
    check_campaign,
    chunk_content_key,
    ingest_provenance,
    load_campaign_metadata,
)
from tasks.lake.store import write_partition

N_IMAGES = 18
runner = CliRunner()


def manifest(folder: Path) -> pd.DataFrame:
    return pd.read_csv(folder / "manifest.csv", dtype=str, keep_default_na=False)


def write_manifest(folder: Path, m: pd.DataFrame) -> None:
    (folder / "manifest.csv").write_text(m.to_csv(index=False))


def edit_metadata(folder: Path, change) -> None:
    meta = json.loads((folder / "campaign.json").read_text())
    change(meta)
    (folder / "campaign.json").write_text(json.dumps(meta))


def faults(images: pd.DataFrame) -> dict[int, tuple[str, str]]:
    """{manifest row: (status, message)} of the faulty rows."""
    bad = images[images["status"] != "ok"]
    return {int(r): (s, m) for r, s, m in zip(bad["manifest_row"], bad["status"], bad["message"], strict=True)}


@contextlib.contextmanager
def within(seconds: int):
    """Fail instead of hanging: SIGALRM after ``seconds``."""
    def timeout(*_):
        raise TimeoutError(f"still running after {seconds} s")
    previous = signal.signal(signal.SIGALRM, timeout)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


@pytest.fixture
def lake_with_partition(tiny_campaign, tmp_path):
    """A lake holding the clean tiny campaign's images partition: (root, its bytes)."""
    root = tmp_path / "results"
    meta, images = check_campaign(tiny_campaign)
    path = write_partition("images", meta["campaign_id"], images, ingest_provenance(tiny_campaign, images), root)
    return root, path.read_bytes()


def assert_cli_refuses(command: str, campaign: Path, root: Path, before: bytes, *fragments: str) -> str:
    """``fivecal <command> <campaign>`` exits 2 with an error naming ``fragments`` and no traceback,
    and the images partition of the tiny campaign is unchanged."""
    result = runner.invoke(app, [command, str(campaign), "--results", str(root)])
    assert result.exit_code == 2, result.output
    assert result.output.startswith("error: ") and "Traceback" not in result.output
    for text in fragments:
        assert text in result.output, result.output
    assert (root / "images" / "campaign_id=tiny" / "part-0.parquet").read_bytes() == before
    return result.output


# --------------------------------------------------------------------------------------------
# campaign.json against its schema


@pytest.mark.parametrize(("change", "key"), [
    (lambda m: m["plates"]["plate_a"].__setitem__("pitch_mm", -11.0), "plates.plate_a.pitch_mm must be a number > 0"),
    (lambda m: m["plates"]["plate_b"].__setitem__("pitch_mm", 0), "plates.plate_b.pitch_mm must be a number > 0"),
    (lambda m: m["plates"]["plate_a"].__setitem__("dot_diameter_mm", -1), "plates.plate_a.dot_diameter_mm"),
    (lambda m: m["plates"]["plate_a"].__setitem__("row_pitch_mm", 0.0), "plates.plate_a.row_pitch_mm"),
    (lambda m: m["plates"]["plate_a"].__setitem__("rows", 2.5), "plates.plate_a.rows must be an integer"),
    (lambda m: m["plates"]["plate_a"].__setitem__("dot_diameter_mm", 20.0), "dots would touch"),
    (lambda m: m["cameras"]["camera1"].__setitem__("pixel_size_mm", 0), "cameras.camera1.pixel_size_mm"),
    (lambda m: m["cameras"]["camera2"].__setitem__("focal_length_mm", "16"), "cameras.camera2.focal_length_mm"),
    (lambda m: m["cameras"]["camera1"].__setitem__("height_px", -512), "cameras.camera1.height_px"),
    (lambda m: m.pop("plates"), "plates must be a non-empty object"),
    (lambda m: m.pop("views"), "views must be a non-empty object"),
    (lambda m: m.pop("cameras"), "cameras must be a non-empty object"),
    (lambda m: m["views"].__setitem__("camera2", "plate_z"), "views.camera2 must name a plate"),
    (lambda m: m["views"].__setitem__("camera3", "plate_a"), "views.camera3 is not a camera"),
    (lambda m: m["machine"]["axes"]["A"].__setitem__("direction", [0, 0, 0]), "machine.axes.A.direction"),
    (lambda m: m["machine"]["attachments"].pop("camera2"), "machine.attachments lacks camera2"),
    (lambda m: m.__setitem__("format_version", True), "format_version True is not supported"),
])
def test_metadata_breaking_the_schema_is_a_campaign_fault_naming_the_key(campaign_copy, change, key):
    c = campaign_copy()
    edit_metadata(c, change)
    with pytest.raises(CampaignError, match=r"campaign\.json: ") as info:
        load_campaign_metadata(c)
    assert key in str(info.value)


def test_the_clean_metadata_builds_the_machine_and_plates_the_analysis_uses(tiny_campaign):
    from tasks.vision.pipeline import campaign_plates, nominal_machine

    meta = load_campaign_metadata(tiny_campaign)
    assert set(campaign_plates(meta)) == set(meta["plates"])
    assert set(nominal_machine(meta).cameras) == set(meta["cameras"])


@pytest.mark.parametrize("command", ["ingest", "measure", "calibrate"])
def test_cli_refuses_a_negative_pitch_before_any_work_and_keeps_the_lake(campaign_copy, lake_with_partition,
                                                                         command):
    c = campaign_copy()
    edit_metadata(c, lambda m: m["plates"]["plate_a"].__setitem__("pitch_mm", -11.0))
    root, before = lake_with_partition
    assert_cli_refuses(command, c, root, before, "plates.plate_a.pitch_mm must be a number > 0 (got -11.0)")


# --------------------------------------------------------------------------------------------
# manifest: vocabulary, capture order, mostly faults


def test_unknown_stage_and_a_group_that_does_not_fit_are_faults(campaign_copy):
    c = campaign_copy()
    m = manifest(c)
    pdge = m.index[m["stage"] == "pdge"][0]
    m.loc[0, "stage"] = "bogus_stage"
    m.loc[1, "group"] = ""
    m.loc[pdge, "group"] = "Q"
    write_manifest(c, m)
    _, images = check_campaign(c)
    got = faults(images)
    assert set(got) == {1, 2, pdge + 1} and {s for s, _ in got.values()} == {"bad_stage"}
    assert "stage 'bogus_stage' is not one of camera_calibration, pdge, pige, validation, verification" in got[1][1]
    assert "group '' does not fit stage camera_calibration" in got[2][1]
    assert "group 'Q' does not fit stage pdge (expected one of X, Y, Z, A, C)" in got[pdge + 1][1]


def test_a_timestamp_out_of_capture_order_or_in_the_future_is_a_row_fault(campaign_copy):
    c = campaign_copy()
    m = manifest(c)
    m.loc[4, "timestamp"] = "2099-01-01T00:00:00Z"     # row 5: in the future
    m.loc[9, "timestamp"] = m.loc[2, "timestamp"]       # row 10: earlier than row 9
    write_manifest(c, m)
    _, images = check_campaign(c)
    got = faults(images)
    assert got[5][0] == "bad_timestamp" and "in the future" in got[5][1]
    assert got[10][0] == "out_of_order" and "is earlier than manifest row 9's" in got[10][1]
    assert set(got) == {5, 10}


def test_reversed_timestamps_are_a_campaign_fault(campaign_copy, lake_with_partition):
    c = campaign_copy()
    m = manifest(c)
    m["timestamp"] = m["timestamp"].iloc[::-1].to_numpy()
    write_manifest(c, m)
    with pytest.raises(CampaignError, match=r"17 of 18 rows are faulty by the manifest alone, more than the 50%"):
        check_campaign(c)
    root, before = lake_with_partition
    assert_cli_refuses("ingest", c, root, before, "manifest.csv: 17 of 18 rows are faulty",
                       "rows must be in capture order")


def test_a_valid_header_followed_by_garbage_is_a_campaign_fault(campaign_copy, lake_with_partition):
    c = campaign_copy()
    header = (c / "manifest.csv").read_text().splitlines()[0]
    garbage = "".join(chr(32 + (i * 7919) % 95) for i in range(200_000)).replace("~", "\n")
    (c / "manifest.csv").write_text(header + "\n" + garbage)
    root, before = lake_with_partition
    assert_cli_refuses("ingest", c, root, before, "manifest.csv: ",
                       "rows have more or fewer fields than the header's 13, more than the 50%",
                       "refused whole, nothing written. First: line 2")


def test_no_usable_image_or_mostly_faulty_images_is_a_campaign_fault(campaign_copy):
    c = campaign_copy()
    paths = manifest(c)["path"]
    for p in paths.iloc[:9]:  # half the images missing: still a campaign, with faults
        (c / p).unlink()
    _, images = check_campaign(c)
    assert (images["status"] == "missing_file").sum() == 9
    (c / paths.iloc[9]).unlink()  # 10 of 18
    with pytest.raises(CampaignError, match=r"10 of 18 rows are faulty \(campaign tiny: 18 images, 8 ok"):
        check_campaign(c)
    for p in paths.iloc[10:]:
        (c / p).unlink()
    with pytest.raises(CampaignError, match=r"no usable image \(campaign tiny: 18 images, 0 ok"):
        check_campaign(c)


# --------------------------------------------------------------------------------------------
# files: format by content, links, devices, pipes, sizes


def test_a_jpeg_named_png_is_wrong_format(campaign_copy):
    c = campaign_copy()
    p = c / manifest(c)["path"].iloc[3]
    p.write_bytes(cv2.imencode(".jpg", cv2.imread(str(p), cv2.IMREAD_UNCHANGED))[1].tobytes())
    _, images = check_campaign(c)
    assert faults(images) == {4: ("wrong_format", f"manifest row 4 ({manifest(c)['path'].iloc[3]}): not a PNG: the "
                                  "content is JPEG (the format is read from the bytes, not the name)")}


def test_links_leaving_the_campaign_are_bad_paths_and_links_inside_are_followed(campaign_copy, tmp_path):
    c = campaign_copy()
    paths = manifest(c)["path"]
    elsewhere = tmp_path / "elsewhere.png"
    shutil.copy(c / paths.iloc[0], elsewhere)
    for i, target in ((0, elsewhere), (1, Path("/etc/passwd"))):
        (c / paths.iloc[i]).unlink()
        os.symlink(target, c / paths.iloc[i])
    inside = c / "images" / "moved.png"  # a link to a file inside the campaign is fine
    (c / paths.iloc[2]).rename(inside)
    os.symlink(Path("..") / "moved.png", c / paths.iloc[2])
    _, images = check_campaign(c)
    got = faults(images)
    assert set(got) == {1, 2} and {s for s, _ in got.values()} == {"bad_path"}
    assert f"path leads outside the campaign folder (to {elsewhere.resolve()}) after following links" in got[1][1]
    assert "(to /etc/passwd)" in got[2][1]


def test_a_link_to_a_device_or_a_pipe_never_hangs(campaign_copy):
    c = campaign_copy()
    paths = manifest(c)["path"]
    (c / paths.iloc[0]).unlink()
    os.symlink("/dev/zero", c / paths.iloc[0])
    (c / paths.iloc[1]).unlink()
    os.mkfifo(c / paths.iloc[1])  # a pipe inside the campaign: nobody ever writes to it
    with within(60):
        rows = manifest(c).assign(manifest_row=range(1, N_IMAGES + 1))[["manifest_row", "path"]]
        chunk_content_key(c, rows)  # the cache key hashes every file: the old hang
        _, images = check_campaign(c)
    got = faults(images)
    assert got[1][0] == "bad_path" and "(to /dev/zero)" in got[1][1]
    assert got[2][0] == "unreadable_file" and "not a regular file (a device, pipe or socket)" in got[2][1]


def test_a_file_over_the_size_limit_is_not_read(campaign_copy, monkeypatch):
    c = campaign_copy()
    paths = manifest(c)["path"]
    limit = max((c / p).stat().st_size for p in paths)
    monkeypatch.setattr(ingest, "MAX_IMAGE_BYTES", limit)
    big = c / paths.iloc[0]
    big.write_bytes(big.read_bytes() + b"\0" * (limit + 1 - big.stat().st_size))  # still decodes: PNG ends at IEND
    _, images = check_campaign(c)
    assert faults(images) == {1: ("unreadable_file", f"manifest row 1 ({paths.iloc[0]}): file too large "
                                  f"({limit + 1} bytes, the limit is {limit})")}


def test_metadata_and_manifest_are_read_the_same_safe_way(campaign_copy, tmp_path):
    c = campaign_copy()
    (c / "manifest.csv").unlink()
    os.symlink("/dev/zero", c / "manifest.csv")
    with within(30), pytest.raises(CampaignError, match=r"manifest\.csv: path leads outside"):
        check_campaign(c)
    (c / "manifest.csv").unlink()
    os.mkfifo(c / "manifest.csv")
    with within(30), pytest.raises(CampaignError, match=r"manifest\.csv: not a regular file"):
        check_campaign(c)
    (c / "campaign.json").unlink()
    os.mkfifo(c / "campaign.json")
    with within(30), pytest.raises(CampaignError, match=r"campaign\.json: cannot read campaign metadata \(not a"):
        check_campaign(c)

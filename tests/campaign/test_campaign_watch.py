"""Finding dropped campaigns (tasks.campaign.watch) and the recalibration ledger
(tasks.campaign.recalibration_ledger): what counts as a campaign, what is skipped and why, the input hash,
and claims that exclude a second run and vanish with a killed one."""

import os
import shutil
import subprocess
import sys
import time

import pytest

from tasks.campaign.recalibration_ledger import Ledger
from tasks.campaign.watch import scan_watch_dir, seconds_since_change


@pytest.fixture
def watch(tmp_path, campaign_copy):
    """A watched folder: campaigns a1 and (filed by year) b2, a copy of a1, a malformed folder, a
    folder still being copied (no manifest yet), a hidden staging folder and a plain folder."""
    w = tmp_path / "watch"
    (w / "2026").mkdir(parents=True)
    campaign_copy("a1").rename(w / "a1")
    campaign_copy("b2").rename(w / "2026" / "b2")
    copy = campaign_copy("a1copy")
    (copy / "campaign.json").write_bytes((w / "a1" / "campaign.json").read_bytes())  # the same campaign again
    copy.rename(w / "zz-copy-of-a1")
    (w / "broken").mkdir()
    (w / "broken" / "campaign.json").write_text("{not json")
    (w / "broken" / "manifest.csv").write_text("image_id\n")
    (w / "copying").mkdir()
    (w / "copying" / "campaign.json").write_text("{}")
    (w / ".c3.partial").mkdir()
    (w / ".c3.partial" / "campaign.json").write_text("{}")
    (w / "notes").mkdir()
    return w


def test_scan_finds_campaigns_and_names_why_others_are_skipped(watch):
    found, skipped = scan_watch_dir(watch)
    assert [(e.campaign_id, os.path.relpath(e.folder, watch)) for e in found] == [("b2", "2026/b2"), ("a1", "a1")]
    assert all(len(e.input_sha256) == 64 and e.missing_images == 0 for e in found)
    reasons = {os.path.relpath(s.folder, watch): s.reason for s in skipped}
    assert set(reasons) == {"broken", "copying", "zz-copy-of-a1"}
    assert "campaign.json: not valid JSON" in reasons["broken"]
    assert "manifest.csv: missing" in reasons["copying"]
    assert reasons["zz-copy-of-a1"].startswith(f"a copy of {watch / 'a1'}")
    # captures/ inside a campaign are campaign folders too, but not campaigns of the watch dir
    (watch / "a1" / "captures" / "x").mkdir(parents=True)
    (watch / "a1" / "captures" / "x" / "campaign.json").write_text("{}")
    assert len(scan_watch_dir(watch)[0]) == 2


def test_same_id_different_content_is_skipped_both_ways(watch):
    manifest = watch / "zz-copy-of-a1" / "manifest.csv"
    manifest.write_text(manifest.read_text() + "\n")  # still valid, other bytes
    found, skipped = scan_watch_dir(watch)
    assert [e.campaign_id for e in found] == ["b2"]
    assert sum("several folders with different content" in s.reason for s in skipped) == 2


def test_input_hash_follows_campaign_json_and_manifest_only(watch):
    shutil.rmtree(watch / "zz-copy-of-a1")
    before = {e.campaign_id: e.input_sha256 for e in scan_watch_dir(watch)[0]}
    image = next((watch / "a1" / "images").rglob("*.png"))
    image.unlink()  # a missing image is ingest's business: same input, counted
    after = scan_watch_dir(watch)[0]
    assert {e.campaign_id: e.input_sha256 for e in after} == before
    assert {e.campaign_id: e.missing_images for e in after} == {"a1": 1, "b2": 0}
    (watch / "a1" / "manifest.csv").write_text((watch / "a1" / "manifest.csv").read_text() + "\n")
    assert {e.campaign_id: e.input_sha256 for e in scan_watch_dir(watch)[0]}["a1"] != before["a1"]


def test_quiet_time_sees_new_files_but_not_captures(tmp_path):
    folder = tmp_path / "c"
    (folder / "images").mkdir(parents=True)
    (folder / "images" / "a.png").write_bytes(b"x")
    old = time.time() - 1000
    for p in (folder / "images" / "a.png", folder / "images", folder):
        os.utime(p, (old, old))
    now = time.time()
    assert seconds_since_change(folder, now + 50) >= 50  # ctime is recent even though mtime is old
    (folder / "captures").mkdir()
    os.utime(folder, (old, old))
    (folder / "captures" / "new.png").write_bytes(b"y")
    assert seconds_since_change(folder, time.time() + 30) >= 29  # captures/ is ignored ...
    (folder / "images" / "b.png").write_bytes(b"z")
    assert seconds_since_change(folder, time.time()) < 5  # ... a new image is not


def test_missing_watch_dir_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="watched directory"):
        scan_watch_dir(tmp_path / "nope")


def test_ledger_records_done_atomically(tmp_path):
    ledger = Ledger.under(tmp_path / "results")
    key = "ab" * 32
    assert not ledger.is_done("c1", key)
    path = ledger.mark_done("c1", key, {"report": "r.html"})
    assert path == tmp_path / "results" / ".recalibration" / "done" / "c1" / f"{key}.json"
    assert ledger.is_done("c1", key) and not ledger.is_done("c1", "cd" * 32)
    assert [(r["campaign_id"], r["report"]) for r in ledger.records()] == [("c1", "r.html")]
    assert not list(path.parent.glob(".*"))  # no temporary file left
    with pytest.raises(ValueError, match="campaign_id"):
        ledger.is_done("../x", key)


def test_claim_excludes_a_second_holder_and_dies_with_its_process(tmp_path):
    ledger = Ledger.under(tmp_path)
    with ledger.claim("c1") as first, ledger.claim("c1") as second, ledger.claim("c2") as other:
        assert (first, second, other) == (True, False, True)
    with ledger.claim("c1") as again:
        assert again  # released at the end of the block
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time\nfrom tasks.campaign.recalibration_ledger import Ledger\n"
        f"with Ledger({str(ledger.folder)!r}).claim('c1') as mine:\n"
        "    print(mine, flush=True)\n    time.sleep(60)\n")], stdout=subprocess.PIPE, text=True,
        cwd=os.path.dirname(os.path.dirname(os.path.dirname(__file__))))
    try:
        assert holder.stdout.readline().strip() == "True"
        with ledger.claim("c1") as mine:
            assert not mine  # another process is calibrating it
        holder.kill()  # a crash mid-calibration ...
        holder.wait(10)
        with ledger.claim("c1") as mine:
            assert mine  # ... leaves nothing stale: the next run takes it
    finally:
        holder.kill()
        holder.wait(10)

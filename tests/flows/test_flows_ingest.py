"""End-to-end tests of the ingest flow (flows/ingest.py) through Prefect's test harness.

The claim: re-ingesting an unchanged campaign decodes no image — every image-check task run ends
in state Cached, as the Prefect API records it — and leaves the images table unchanged; changing
one file re-runs only its chunk. A campaign-level fault fails the flow and writes nothing.
"""

from __future__ import annotations

import time
from uuid import UUID

import pandas as pd
import pytest

from flows.ingest import ingest_campaign, run_ingest
from tasks.campaign.ingest import CHUNK_SIZE, CampaignError
from tasks.lake.store import read_provenance, read_table

pytestmark = pytest.mark.flow

N_IMAGES = 18  # the tiny campaign (tests/conftest.py)


def chunk_task_states(flow_run_id: UUID, expected: int, timeout_s: float = 20.0) -> list[str]:
    """State names of the flow run's image-check task runs, read back through the Prefect API.

    Task-run states reach the API asynchronously (as events), so poll until ``expected`` runs
    are final."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterId
    from prefect.client.schemas.sorting import TaskRunSort

    deadline = time.monotonic() + timeout_s
    while True:
        with get_client(sync_client=True) as client:
            runs = client.read_task_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=[flow_run_id])),
                                         sort=TaskRunSort.NAME_ASC, limit=200)
        states = [r.state.name for r in runs if r.name.startswith("check-images") and r.state is not None]
        if len(states) == expected and all(r.state.is_final() for r in runs if r.name.startswith("check-images")):
            return sorted(states)
        if time.monotonic() > deadline:
            return sorted(states)
        time.sleep(0.2)


def run(campaign, results_root, chunk_size=CHUNK_SIZE):
    state = ingest_campaign(str(campaign), str(results_root), chunk_size=chunk_size, return_state=True)
    assert state.is_completed(), state
    return state.result(), state.state_details.flow_run_id


def test_reingesting_an_unchanged_campaign_is_cached_and_changes_nothing(prefect_harness, campaign_copy, tmp_path):
    from prefect.settings import PREFECT_LOCAL_STORAGE_PATH, temporary_settings

    campaign = campaign_copy("flowcache")
    root = tmp_path / "results"
    chunk_size = 5
    n_chunks = -(-N_IMAGES // chunk_size)  # 4
    # an empty result storage of its own, so that no other test of the session has cached these bytes
    with temporary_settings(updates={PREFECT_LOCAL_STORAGE_PATH: tmp_path / "storage"}):
        first, first_id = run(campaign, root, chunk_size)
        assert first["n_images"] == N_IMAGES and first["by_status"] == {"ok": N_IMAGES}
        assert (first["chunks"], first["chunks_cached"]) == (n_chunks, 0)
        assert chunk_task_states(first_id, n_chunks) == ["Completed"] * n_chunks
        table_1 = read_table("images", root)
        provenance_1 = read_provenance("images", "flowcache", root)
        assert len(table_1) == N_IMAGES and (table_1["campaign_id"] == "flowcache").all()

        second, second_id = run(campaign, root, chunk_size)
        assert second_id != first_id
        assert second["chunks_cached"] == n_chunks
        assert chunk_task_states(second_id, n_chunks) == ["Cached"] * n_chunks
        pd.testing.assert_frame_equal(read_table("images", root), table_1)
        assert read_provenance("images", "flowcache", root) == provenance_1

        # one damaged file (manifest row 7, chunk 2): only its chunk is checked again
        victim = campaign / "images" / "camera1" / "img00006.png"
        victim.write_bytes(victim.read_bytes()[:1000])
        third, third_id = run(campaign, root, chunk_size)
        assert third["by_status"] == {"ok": N_IMAGES - 1, "corrupt_image": 1}
        assert chunk_task_states(third_id, n_chunks) == ["Cached"] * (n_chunks - 1) + ["Completed"]
        table_3 = read_table("images", root).set_index("image_id")
        assert table_3.loc["img00006", "status"] == "corrupt_image"
        assert table_3.loc["img00006", "message"].startswith("manifest row 7 (images/camera1/img00006.png): ")
        assert read_provenance("images", "flowcache", root)["input_sha256"] != provenance_1["input_sha256"]


def test_results_are_persisted_in_the_sessions_own_storage(prefect_harness, campaign_copy, tmp_path):
    run(campaign_copy("storage"), tmp_path / "results")
    assert any(p.is_file() for p in prefect_harness.iterdir())


def test_campaign_level_fault_fails_the_flow_and_writes_nothing(prefect_harness, campaign_copy, tmp_path):
    campaign = campaign_copy("empty")
    header = (campaign / "manifest.csv").read_text().splitlines()[0]
    (campaign / "manifest.csv").write_text(header + "\n")
    root = tmp_path / "results"
    with pytest.raises(CampaignError, match=r"manifest\.csv: no image rows \(empty campaign\)"):
        run_ingest(campaign, root)
    assert not root.exists()


def test_mostly_faulty_images_fail_the_flow_and_keep_the_previous_partition(prefect_harness, campaign_copy,
                                                                            tmp_path):
    import cv2

    campaign = campaign_copy("mostly")
    root = tmp_path / "results"
    run(campaign, root)
    part = root / "images" / "campaign_id=mostly" / "part-0.parquet"
    before = part.read_bytes()
    paths = pd.read_csv(campaign / "manifest.csv", dtype=str)["path"]
    for p in paths.iloc[:10]:  # 10 of 18 images re-encoded as JPEG under their .png names
        image = cv2.imread(str(campaign / p), cv2.IMREAD_UNCHANGED)
        (campaign / p).write_bytes(cv2.imencode(".jpg", image)[1].tobytes())
    with pytest.raises(CampaignError, match=r"10 of 18 rows are faulty \(campaign mostly: 18 images, 8 ok, 10 faults "
                                            r"\(wrong_format 10\)\), more than the 50%"):
        run_ingest(campaign, root)
    assert part.read_bytes() == before

"""Shared fixtures.

- ``tiny_campaign``: an 18-image simulated campaign (small image size, 768×512 px), written once
  per session by the science functions directly (no Prefect run), so tests never depend on /tmp.
- ``campaign_copy``: a factory copying it into the test's tmp_path under a new campaign_id, for
  tests that damage it.
- ``prefect_harness``: ONE Prefect test harness (temporary server and database) per session,
  with its own result storage (PREFECT_LOCAL_STORAGE_PATH) in a tmp folder. Flow tests use it.
- ``calibrated_campaign``: a 47-image campaign calibrated once (``fivecal calibrate``) per test
  run — shared by the xdist workers — with its lake and report. Read-only: copy it to change it.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import NamedTuple

import pytest

from tasks.machine.description import load_machine
from tasks.simulation.prototype_errors import load_prototype_errors

TINY_CAMPAIGN_ID = "tiny"
TINY_SEED = 0


def write_tiny_campaign(folder: Path, campaign_id: str = TINY_CAMPAIGN_ID, seed: int = TINY_SEED) -> Path:
    """Simulate a tiny campaign into ``folder`` (18 images: 2 calibration views per camera, 2
    positions of each axis sweep (3 of C: both stroke ends and home), 2 PIGE and 1 validation pose),
    as ``fivecal simulate`` would write it at ``--size small``, truth included. Science functions
    only; about half a second."""
    from tasks.simulation.campaign_plan import CampaignPlan
    from tasks.simulation.simulate import write_campaign

    plan = CampaignPlan(calibration_trials=1, images_per_trial=2, sweep_positions=2, sweep_repeats=1,
                        pige_poses=2, validation_poses=1)
    return write_campaign(folder, campaign_id, seed=seed, size="small", plan=plan)


@pytest.fixture(scope="session")
def tiny_campaign(tmp_path_factory) -> Path:
    """A pristine tiny campaign (do not modify: use ``campaign_copy``)."""
    return write_tiny_campaign(tmp_path_factory.mktemp("campaigns") / TINY_CAMPAIGN_ID)


@pytest.fixture
def campaign_copy(tiny_campaign, tmp_path) -> Callable[..., Path]:
    """``campaign_copy(campaign_id="tiny")``: a fresh copy of the tiny campaign in tmp_path,
    with ``campaign_id`` set in its campaign.json."""

    def make(campaign_id: str = TINY_CAMPAIGN_ID) -> Path:
        dest = tmp_path / "campaigns" / campaign_id
        shutil.copytree(tiny_campaign, dest)
        meta_path = dest / "campaign.json"
        meta = json.loads(meta_path.read_text())
        meta["campaign_id"] = campaign_id
        meta_path.write_text(json.dumps(meta, indent=1))
        return dest

    return make


@pytest.fixture(scope="session")
def prefect_harness(tmp_path_factory) -> Iterator[Path]:
    """Run flows against a temporary Prefect server; yields the session's result storage folder.

    The storage path is set in the environment (seen by any subprocess) and, because Prefect
    reads its settings when it is imported, also as a temporary setting of this process. The
    temporary server sends no telemetry and is given as long to start as the CLI gives it.
    """
    from prefect.settings import PREFECT_LOCAL_STORAGE_PATH, PREFECT_SERVER_ANALYTICS_ENABLED, temporary_settings
    from prefect.testing.utilities import prefect_test_harness

    from fivecal.prefect_defaults import SERVER_STARTUP_TIMEOUT_S

    storage = tmp_path_factory.mktemp("prefect-storage")
    previous = os.environ.get("PREFECT_LOCAL_STORAGE_PATH")
    os.environ["PREFECT_LOCAL_STORAGE_PATH"] = str(storage)
    try:
        settings = {PREFECT_LOCAL_STORAGE_PATH: storage, PREFECT_SERVER_ANALYTICS_ENABLED: False}
        with (temporary_settings(updates=settings),
              prefect_test_harness(server_startup_timeout=SERVER_STARTUP_TIMEOUT_S)):
            yield storage
    finally:
        if previous is None:
            os.environ.pop("PREFECT_LOCAL_STORAGE_PATH", None)
        else:
            os.environ["PREFECT_LOCAL_STORAGE_PATH"] = previous


@pytest.fixture(scope="session")
def machine():
    """The prototype machine description (tasks/machine/machines/prototype.json)."""
    return load_machine("prototype")


@pytest.fixture(scope="session")
def errors():
    """The prototype's frozen true errors."""
    return load_prototype_errors()


CALIBRATED_CAMPAIGN_ID = "calibrated"


class CalibratedCampaign(NamedTuple):
    campaign: Path   # the campaign folder
    results: Path    # its results lake root (every table of ingest, measure and calibrate)
    reports: Path    # reports root: the report is reports/<campaign_id>/fixture/
    summary: dict    # calibrate_campaign's return value (JSON round-tripped)


@contextlib.contextmanager
def _exclusive(lock_file: Path) -> Iterator[None]:
    with open(lock_file, "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


@pytest.fixture(scope="session")
def calibrated_campaign(tmp_path_factory, request) -> CalibratedCampaign:
    """A small simulated campaign (47 images: 1 calibration trial of 6 views per camera, 4 positions
    per axis sweep, 12 five-axis and 3 validation poses) run once through
    ``flows.calibrate.calibrate_campaign`` (run name "fixture"); about 25 s plus the Prefect server.

    Computed once per test run: under pytest-xdist the first worker to need it calibrates (under
    its ``prefect_harness``) while the others wait on a file lock, then every worker reads the
    same folders. Do not modify them. The calibration's numbers may be poor (the science is being
    reworked): use it for structure and contracts, not accuracy.
    """
    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    root = shared / "calibrated_campaign"
    done = root / "summary.json"
    with _exclusive(shared / "calibrated_campaign.lock"):
        if not done.exists():
            request.getfixturevalue("prefect_harness")
            from flows.calibrate import calibrate_campaign
            from tasks.simulation.campaign_plan import CampaignPlan
            from tasks.simulation.simulate import write_campaign

            shutil.rmtree(root, ignore_errors=True)
            plan = CampaignPlan(calibration_trials=1, images_per_trial=6, sweep_positions=4, sweep_repeats=1,
                                pige_poses=12, validation_poses=3)
            folder = write_campaign(root / "campaigns" / CALIBRATED_CAMPAIGN_ID, CALIBRATED_CAMPAIGN_ID, seed=1,
                                    size="small", plan=plan)
            summary = calibrate_campaign(str(folder), results_root=str(root / "results"),
                                         reports_root=str(root / "reports"), run="fixture")
            done.write_text(json.dumps(summary, default=str))
    return CalibratedCampaign(root / "campaigns" / CALIBRATED_CAMPAIGN_ID, root / "results", root / "reports",
                              json.loads(done.read_text()))

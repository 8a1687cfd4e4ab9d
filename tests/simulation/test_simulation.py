"""The virtual machine: the prototype's error magnitudes, the campaign plan, deterministic images."""

import numpy as np
import pytest

from tasks.machine.effects import parse_effect
from tasks.simulation.campaign_plan import CampaignPlan, five_axis_poses, plan_campaign
from tasks.simulation.prototype_errors import load_prototype_errors
from tasks.simulation.simulate import encode_png, manifest_from_plan, render_image, simulate_truth
from tasks.simulation.truth_stats import SEED_BEFORE, summarise, tip_errors
from tasks.vision.detection.framework import cut_by_border
from tasks.vision.detection.partial_view import MIN_FRACTION


def test_prototype_reproduces_the_seeds_before_compensation_errors(machine):
    cmds = five_axis_poses(machine, 100, CampaignPlan(), np.random.default_rng([0, 3]))
    stats = summarise(tip_errors(machine, cmds, load_prototype_errors()))
    assert stats["position_mean_um"] == pytest.approx(SEED_BEFORE["position_mean_um"], rel=0.10)
    assert stats["orientation_mean_arcsec"] == pytest.approx(SEED_BEFORE["orientation_mean_arcsec"], rel=0.15)


def test_statistics_hold_on_independent_validation_poses(machine):
    cmds = five_axis_poses(machine, 300, CampaignPlan(), np.random.default_rng([99, 3]))
    stats = summarise(tip_errors(machine, cmds, load_prototype_errors()))
    assert stats["position_mean_um"] == pytest.approx(59.9, rel=0.10)
    assert stats["orientation_mean_arcsec"] == pytest.approx(160.0, rel=0.15)


@pytest.fixture(scope="module")
def default_plan(machine):
    return plan_campaign(machine, CampaignPlan(), seed=0)


def test_default_plan_has_the_seeds_stage_sizes(default_plan):
    plan, fixture = default_plan
    counts = plan.groupby(["stage", "camera"]).size().to_dict()
    assert counts[("camera_calibration", "camera1")] == 150 and counts[("camera_calibration", "camera2")] == 150
    assert counts[("pige", "camera1")] == 300 and counts[("validation", "camera1")] == 100
    sweeps = plan[plan.stage == "pdge"].groupby("group").size().to_dict()
    assert sweeps == {"X": 250, "Y": 250, "Z": 250, "A": 250, "C": 255}  # C: 51 positions, both stroke ends
    assert len(fixture) == 300
    per_trial = plan[plan.stage == "camera_calibration"].groupby(["camera", "group"]).size()
    assert per_trial.eq(15).all() and len(per_trial) == 20


def test_sweeps_step_as_planned_and_alternate_direction(default_plan):
    """X/Y/A as the seed; Z in 0.2 mm steps and C over its whole stroke, ends included (campaign_plan)."""
    plan, _ = default_plan
    for axis, step in {"X": 1.0, "Y": 1.0, "Z": 0.2, "A": 1.0, "C": 7.2}.items():
        s = plan[(plan.stage == "pdge") & (plan.group == axis)]
        first = s[s.repeat == 0][axis].to_numpy()
        assert np.allclose(np.diff(first), step) and 0.0 in first and len(first) == (51 if axis == "C" else 50)
        assert np.allclose(s[s.repeat == 1][axis].to_numpy(), first[::-1])
        others = [a for a in "XYZAC" if a != axis]
        assert np.allclose(s[others].to_numpy(), 0.0)


def test_every_planned_view_keeps_enough_of_its_plate_in_the_image(machine, default_plan):
    """Calibration views and camera 2's A sweep see their whole plate; plate a (66 mm) leaves camera 1's
    field only in the Y sweep's ends and where C turns its corners out, and every view keeps at least
    the half of its dots that detection needs wholly inside the image (tasks.vision.detection.partial_view)."""
    plan, fixture = default_plan
    errors = load_prototype_errors()
    truth = simulate_truth(machine, errors, plan, fixture, size="full")
    partial_groups = set(plan.loc[~truth.in_view, "group"])
    assert partial_groups == {"Y", "C", "pige", "validation"}
    camera = machine.cameras["camera1"]
    for i in np.flatnonzero(~truth.in_view):
        plate = machine.plates[truth.plate_names[i]]
        radius_px = plate.dot_diameter_mm / 2 * camera.fx_px / truth.T_cam_plate[i][2, 3]
        inside = ~cut_by_border(truth.centres_px[i], np.full(len(truth.centres_px[i]), radius_px),
                                plate.pitch_mm / plate.dot_diameter_mm - 1.0, (camera.height_px, camera.width_px))
        assert inside.sum() >= MIN_FRACTION * plate.rows * plate.cols, plan.iloc[i]


def test_five_axis_poses_stay_inside_the_swept_ranges(default_plan):
    plan, _ = default_plan
    sweeps = plan[plan.stage == "pdge"]
    five_axis = plan[plan.stage.isin(["pige", "validation"])]
    for axis in "XYZA":
        swept = sweeps[sweeps.group == axis][axis]
        assert five_axis[axis].between(swept.min(), swept.max()).all(), axis


def test_the_context_plan_takes_both_directions_in_each_of_two_passes_an_hour_apart(machine):
    """CampaignPlan.context(): each pass holds one repeat of every sweep (forward, then backward) and
    half the five-axis poses; the second pass starts 50 minutes after the first ends, and the
    coarse sweeps still span the five-axis poses."""
    plan, _ = plan_campaign(machine, CampaignPlan.context(), seed=3)
    assert len(plan) == 206
    gap = np.diff(plan["time_s"].to_numpy())
    assert np.sort(gap)[-1] == pytest.approx(3000.0 + 3.0) and np.sort(gap)[-2] == pytest.approx(3.0)
    second = plan["time_s"].to_numpy() > plan["time_s"].to_numpy()[np.argmax(gap)]
    for part, repeat in ((~second, 0), (second, 1)):
        sweeps = plan[part & (plan.stage == "pdge")]
        assert set(sweeps.repeat) == {repeat} and set(sweeps.group) == set("XYZAC")
        assert (plan[part].stage == "pige").sum() == 24
    assert set(plan[second].stage) >= {"validation"} and not (plan[~second].stage == "validation").any()
    sweeps = plan[plan.stage == "pdge"]
    five_axis = plan[plan.stage.isin(["pige", "validation"])]
    for axis in "XYZA":
        swept = sweeps[sweeps.group == axis][axis]
        assert five_axis[axis].between(swept.min(), swept.max()).all(), axis


def test_same_seed_gives_byte_identical_images(machine):
    plan, fixture = plan_campaign(machine, CampaignPlan.small(), seed=5)
    errors = load_prototype_errors()
    errors.effects = [parse_effect("focal_drift:ppm_per_mm=40")]
    truth = simulate_truth(machine, errors, plan, fixture, size="small")
    rows = [0, 40, len(plan) - 1]
    a = [encode_png(render_image(machine, truth, plan.camera.iloc[i], i, seed=5)) for i in rows]
    b = [encode_png(render_image(machine, truth, plan.camera.iloc[i], i, seed=5)) for i in rows]
    c = [encode_png(render_image(machine, truth, plan.camera.iloc[i], i, seed=6)) for i in rows]
    assert a == b
    assert all(x != y for x, y in zip(a, c, strict=True))


def test_manifest_carries_commands_time_and_temperature(machine):
    plan, _ = plan_campaign(machine, CampaignPlan.small(), seed=1)
    m = manifest_from_plan(plan)
    assert list(m.columns[:6]) == ["image_id", "path", "camera", "stage", "group", "repeat"]
    assert m.timestamp.is_monotonic_increasing and m.timestamp.str.endswith("Z").all()
    assert m.temperature_c.between(19.0, 22.0).all() and m.temperature_c.nunique() > 10


def test_a_verification_capture_plan_takes_its_repeats_as_passes_over_the_poses():
    from tasks.simulation.verification_capture import capture_plan

    commands = np.arange(10.0).reshape(2, 5)
    plan = capture_plan(["a", "b"], commands, "camera1", start_s=100.0, seconds_per_image=3.0, repeats=3)
    assert plan["image_id"].tolist() == ["a_v", "b_v", "a_v1", "b_v1", "a_v2", "b_v2"]
    assert plan["repeat"].tolist() == [0, 0, 1, 1, 2, 2]
    np.testing.assert_array_equal(plan[["X", "Y", "Z", "A", "C"]].to_numpy(), np.tile(commands, (3, 1)))
    np.testing.assert_allclose(plan["time_s"], 100.0 + 3.0 * np.arange(6))
    with pytest.raises(ValueError, match="at least 1"):
        capture_plan(["a"], commands[:1], "camera1", 0.0, 3.0, repeats=0)

"""The §4.3 inspection and §4.1 centres on rendered dots, against the renderer's truth; bad inputs."""

import re

import cv2
import numpy as np
import pandas as pd
import pytest

from tasks.dispensing.dot_render import DotShape, Lighting, RingScene, random_dot, render_scene
from tasks.dispensing.inspection import inspect_regions, inspect_ring_image, load_config
from tasks.dispensing.measure import inspect_capture

PX_PER_MM = 1 / 0.045
CROP = (128, 128)
RING = (63.3, 64.1)


@pytest.fixture(scope="module")
def cfg():
    return load_config()


def _scene(dots, ring=RING):
    return RingScene(ring, np.diag([PX_PER_MM, -PX_PER_MM]), 2.4, 3.4, tuple(dots))


def test_good_dots_centre_diameter_and_nsd(cfg):
    rng = np.random.default_rng(7)
    errors, diam, nsd = [], [], []
    for i in range(16):
        dot = random_dot(rng, rng.uniform(-0.08, 0.08, 2), 0.8)
        scene = _scene([dot])
        gray = render_scene(scene, CROP, Lighting(contrast=40.0 * (-1) ** i), rng)
        result = inspect_ring_image(gray, cfg)
        assert result.qualified, result.reason
        assert result.polarity == ("bright" if i % 2 == 0 else "dark")
        assert np.hypot(result.ring.x_px - RING[0], result.ring.y_px - RING[1]) < 0.03
        errors.append([result.dot.x_px, result.dot.y_px] - scene.dot_px(dot))
        diam.append(result.dot.diameter_px / (dot.equivalent_diameter_mm() * PX_PER_MM) - 1)
        nsd.append(result.dot.nsd_r - dot.nsd_r())
    assert np.sqrt(np.mean(np.square(errors))) < 0.05  # px per axis
    assert np.abs(diam).max() < 0.015 and abs(np.mean(diam)) < 0.01
    assert abs(np.mean(nsd)) < 0.005


@pytest.mark.parametrize("defect, reasons", [("satellite", ("2 dots in the ring", "circularity")),
                                             ("void", ("CoV_I",)), ("smear", ("NSD_r",)), ("missing", ("no dot",))])
def test_each_defect_is_found(cfg, defect, reasons):
    rng = np.random.default_rng(11)
    dot = random_dot(rng, (0.02, -0.03), 0.8, defect)
    for contrast in (40.0, -40.0):
        gray = render_scene(_scene([] if defect == "missing" else [dot]), CROP, Lighting(contrast=contrast), rng)
        result = inspect_ring_image(gray, cfg)
        # a satellite close to its dot merges with it in the binary image: then its outline fails
        assert not result.qualified and any(r in result.reason for r in reasons), result.reason


def test_bad_inputs_say_what_is_wrong(cfg):
    rng = np.random.default_rng(3)
    blank = np.clip(rng.normal(150, 3, CROP), 0, 255).astype(np.uint8)
    assert inspect_ring_image(blank, cfg).reason == "no ring"
    two = [DotShape((-0.45, 0.0), 0.35), DotShape((0.45, 0.0), 0.35)]
    assert inspect_ring_image(render_scene(_scene(two), CROP, Lighting(), rng), cfg).reason == "2 dots in the ring"
    at_edge = [DotShape((0.95, 0.0), 0.4)]  # runs into the ring
    result = inspect_ring_image(render_scene(_scene(at_edge), CROP, Lighting(), rng), cfg)
    assert not result.qualified and "touches the border" in result.reason


def test_whole_image_mode_excludes_border_regions(cfg):
    rng = np.random.default_rng(5)
    scene = RingScene((0.0, 0.0), np.diag([PX_PER_MM, PX_PER_MM]), 0.0, 0.0,
                      (DotShape((1.4, 1.4), 0.4), DotShape((0.0, 1.4), 0.4)))  # the second one is cut by the edge
    regions, polarity, _ = inspect_regions(render_scene(scene, CROP, Lighting(ring=150.0), rng), cfg)
    assert polarity == "bright"
    assert sorted(r.touches_border for r in regions) == [False, True]
    assert [r.qualified for r in regions if r.touches_border] == [False]


def test_config_file_overrides_and_errors(tmp_path):
    good = tmp_path / "good.toml"
    good.write_text("[inspection]\nnsd_r_max = 0.08\n")
    assert load_config(good).nsd_r_max == 0.08 and load_config(good).cov_i_max == load_config().cov_i_max
    bad = tmp_path / "bad.toml"
    bad.write_text("[inspection]\nnsd_max = 0.08\n")
    with pytest.raises(ValueError, match=r"bad\.toml.*nsd_max"):
        load_config(bad)


def test_capture_rows_record_unreadable_images(tmp_path, cfg):
    rng = np.random.default_rng(2)
    (tmp_path / "images").mkdir()
    image = render_scene(_scene([DotShape((0, 0), 0.4)]), CROP, Lighting(), rng)
    cv2.imwrite(str(tmp_path / "images" / "a.png"), image)
    manifest = pd.DataFrame({"image_id": ["a", "b"], "path": ["images/a.png", "images/b.png"]})
    rows = inspect_capture(tmp_path, manifest, cfg)
    assert rows["qualified"].tolist() == [True, False]
    assert "images/b.png missing or unreadable" in rows["reason"][1]


def test_inspect_command_prints_the_ring_and_its_dot(tmp_path):
    from typer.testing import CliRunner

    from fivecal.cli import app

    rng = np.random.default_rng(4)
    cv2.imwrite(str(tmp_path / "ring.png"), render_scene(_scene([DotShape((0.1, 0.0), 0.4)]), CROP, Lighting(), rng))
    out = CliRunner().invoke(app, ["inspect", str(tmp_path / "ring.png")])
    assert out.exit_code == 0, out.output
    x, y = map(float, re.search(r"ring: centre \(([\d.]+), ([\d.]+)\)", out.output).groups())
    assert abs(x - RING[0]) < 0.05 and abs(y - RING[1]) < 0.05
    assert "polarity: bright; 1 dot(s)" in out.output
    assert "qualified" in out.output.splitlines()[-1]
    bad = CliRunner().invoke(app, ["inspect", str(tmp_path / "nothing.png")])
    assert bad.exit_code == 2 and "not a readable image" in bad.output


def test_lab_request_round_trip_and_manifest_errors(tmp_path):
    from tasks.dispensing.capture import PLAN_FILE, plan_rows, write_plan
    from tasks.dispensing.measure import REQUIRED, load_capture_manifest

    centres = np.array([[1.0, 2.0], [3.0, -4.0]])
    commands = np.arange(10, dtype=float).reshape(2, 5)
    rows = plan_rows("compensated", centres, np.array([19.0, 21.0]), commands, commands + 1)
    assert list(rows["image_id"]) == ["compensated_ring000", "compensated_ring001"]
    assert list(rows["surface_z_mm"]) == [19.0, 21.0]
    plan = write_plan(tmp_path / "cap", rows)
    assert plan.name == PLAN_FILE
    pd.read_csv(plan).to_csv(tmp_path / "cap" / "manifest.csv", index=False)  # the lab's manifest: full frames
    manifest = load_capture_manifest(tmp_path / "cap")
    assert set(REQUIRED) <= set(manifest.columns) and (manifest["roi_x0"] == 0).all()
    pd.read_csv(plan).drop(columns=["image_C_deg"]).to_csv(tmp_path / "cap" / "manifest.csv", index=False)
    with pytest.raises(ValueError, match=r"manifest\.csv.*image_C_deg"):
        load_capture_manifest(tmp_path / "cap")

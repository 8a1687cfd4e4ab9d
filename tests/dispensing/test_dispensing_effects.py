"""The dispensing test reads a calibration that added a user-written effect family
(``--add-effect`` from ``--effect-module``): the modules it recorded, or the ones passed again."""

from pathlib import Path

import pytest

from tasks.machine.effects import EFFECTS, recorded_effects

USER_MODULE = Path(__file__).resolve().parents[2] / "docs" / "examples" / "cross_backlash.py"
SPECS = ["cross_backlash:axis=X,along=Y,amount_um=6", "backlash:axis=Z,amount_um=3,amount_arcsec=0"]


@pytest.fixture
def clean_catalogue():
    before = dict(EFFECTS)
    yield
    EFFECTS.clear()
    EFFECTS.update(before)


def test_the_recorded_modules_define_the_calibrations_user_family(clean_catalogue):
    assert "cross_backlash" not in EFFECTS
    effects = recorded_effects(SPECS, [str(USER_MODULE)])
    assert [e.spec() for e in effects] == SPECS
    assert effects[0]["amount_um"] == 6.0


def test_a_module_passed_again_replaces_a_recorded_one_that_moved(clean_catalogue, tmp_path):
    moved = tmp_path / "gone" / "cross_backlash.py"
    with pytest.raises(ValueError, match=r"could not be imported.*--effect-module"):
        recorded_effects(SPECS, [str(moved)])
    assert [e.spec() for e in recorded_effects(SPECS, [str(moved)], [str(USER_MODULE)])] == SPECS


def test_a_user_family_without_its_module_is_a_clear_error(clean_catalogue):
    with pytest.raises(ValueError, match=r"unknown effect family 'cross_backlash'.*--effect-module"):
        recorded_effects(SPECS, [])
    assert [e.spec() for e in recorded_effects(SPECS[1:], [])] == SPECS[1:]  # the catalogue needs none

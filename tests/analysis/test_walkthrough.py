"""docs/walkthrough.md's story, as docs/examples/walkthrough.py tells it at pose level on the small plan (no
images, no Prefect): the diagnosis ranks the hidden backlash of X first at its size, and adding it brings the
cross-validated RMS and the compensated true tip error down to the campaign without it."""

import importlib.util
import sys
from pathlib import Path

import pytest

from tasks.machine.effects import parse_effect

SCRIPT = Path(__file__).resolve().parents[2] / "docs" / "examples" / "walkthrough.py"


@pytest.fixture(scope="module")
def story():
    spec = importlib.util.spec_from_file_location("walkthrough", SCRIPT)
    walkthrough = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = walkthrough  # its dataclass looks its module up there
    spec.loader.exec_module(walkthrough)
    return walkthrough.pose_story("small", seed=7)


def test_the_walkthrough_finds_the_hidden_backlash_and_adding_it_brings_the_error_down(story):
    top = story.diagnosis.iloc[0]
    found = parse_effect(story.added)
    assert (top.family, top.axis, found.family, found["axis"]) == ("backlash", "X", "backlash", "X")
    assert found["amount_um"] == pytest.approx(10.0, rel=0.1)
    ladder = story.ladder.set_index(["campaign", "model"])
    base = ladder.loc[("hidden", "base")]
    added = ladder.loc[("hidden", f"+ {story.added}")]
    clean = ladder.loc[("clean", "base")]
    # the fit explains the campaign as well as the one without the effect, on poses it did not see
    assert added.cv_rms < 0.5 * base.cv_rms
    assert added.cv_rms < 1.2 * clean.cv_rms
    assert added.sigma2 < 1.5 * clean.sigma2 < base.sigma2
    # and the compensated tip comes back to the clean campaign's
    assert added.true_tip_after_um < base.true_tip_after_um - 1.0
    assert added.true_tip_after_um < 1.2 * clean.true_tip_after_um
    # after adding it nothing else is accepted
    assert not story.after.accepted.any()

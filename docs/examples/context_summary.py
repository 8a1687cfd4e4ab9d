"""Print the tip errors of the context walk-through (docs/effects.md, "Measured at the tip"): per campaign,
each model-ladder step with its cross-validated RMS and the tip error after compensating with that step's
model (VBM and truth), the true tip error before compensation and how far the hidden effect moves it there
(against the clean campaign of the same seed, pose by pose), how far the last compensation's true tip sits
from the clean campaign's, and the ratio of the last step to the clean campaign of the same seed.

    python docs/examples/context_summary.py RESULTS_ROOT CAMPAIGN_ID...   # clean-s<seed> are the references
"""

import sys

import pandas as pd

from tasks.analysis.model_ladder import read_ladder
from tasks.lake.store import read_table


def _truth(root: str, cid: str, phase: str) -> pd.DataFrame:
    v = read_table("verification", root, cid)
    return v[(v["phase"] == phase) & (v["source"] == "truth")].set_index("image_id")[["dx_um", "dy_um", "dz_um"]]


def _shift(root: str, cid: str, phase: str) -> float:
    """Mean over the validation poses of how far the true tip sits from the clean campaign's of the
    same seed (same poses), ‖Δ(dx, dy, dz)‖ in µm: before compensation, what the hidden effect moves it;
    after, what the effect and what the fit made of it leave (the campaign's last compensation)."""
    clean = "clean-" + cid.rsplit("-", 1)[-1]
    a, b = _truth(root, cid, phase), _truth(root, clean, phase)
    return float(((a - b.loc[a.index]) ** 2).sum(axis=1).pow(0.5).mean())


def summary(root: str, campaign_ids: list[str]) -> pd.DataFrame:
    rows = []
    for cid in campaign_ids:
        ladder = read_ladder(cid, root)
        verification = read_table("verification", root, cid)
        before = verification[(verification["phase"] == "before") & (verification["source"] == "truth")]
        for r in ladder.itertuples(index=False):
            rows.append({"campaign": cid, "step": r.step, "effects": r.effect_specs or "-", "cv_rms": r.cv_rms,
                         "before_truth_um": before["position_um"].mean(),
                         "after_vbm_um": r.compensated_vbm_position_um,
                         "after_truth_um": r.compensated_truth_position_um,
                         "after_vbm_arcsec": r.compensated_vbm_orientation_arcsec,
                         "after_truth_arcsec": r.compensated_truth_orientation_arcsec})
    out = pd.DataFrame(rows)
    out["before_truth_shift_um"] = out["campaign"].map({cid: _shift(root, cid, "before") for cid in campaign_ids})
    last = out.groupby("campaign")["step"].transform("max") == out["step"]
    out.loc[last, "after_truth_shift_um"] = out.loc[last, "campaign"].map(
        {cid: _shift(root, cid, "after") for cid in campaign_ids})
    seed = out["campaign"].str.extract(r"-(s\d+)$")[0]
    clean = out[out["campaign"].str.startswith("clean-")].groupby(seed).last()
    for q in ("after_vbm_um", "after_truth_um"):
        out[f"{q}/clean"] = out[q] / seed.map(clean[q])
    return out


if __name__ == "__main__":
    pd.set_option("display.width", 250, "display.max_colwidth", 70)
    print(summary(sys.argv[1], sys.argv[2:]).round(3).to_string(index=False))

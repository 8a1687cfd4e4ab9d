"""Drift of the identified errors across campaigns, and whether the machine needs recompensation.

Science only (no Prefect). SYNOPSIS::

    from tasks.analysis.drift import DriftTolerance, drift_table, verification_summary, verdict
    from tasks.lake.store import read_table
    drift = drift_table(read_table("pige"), read_table("pdge"), read_table("images"), DriftTolerance())
    summary = verification_summary(read_table("verification"), read_table("compensation"))
    words = verdict(drift, summary, DriftTolerance())

What is compared: every campaign's quantities against the same quantities of a **reference
campaign** (by default the earliest by capture time; in a lab, the campaign whose compensation the
machine currently runs). The quantities are

- each row of the ``pige`` table (the PIGEs of Table 2 and the constant, squareness and mount (camera, plate)
  parameters fitted with them): its value and standard uncertainty as identified, in µm or arcsec;
  an unidentifiable parameter has no value and is not compared;
- per axis and PDGE component (δx, δy, δz in µm; εx, εy, εz in arcsec; the ``pdge`` table's
  measured error motion referred to home) three statistics over the sweep positions, with their
  standard uncertainty propagated to first order from the positions' standard errors ``std_<c>``
  (taken as independent):

  ============  ==============================================  ============================================
  statistic     value                                           standard uncertainty
  ============  ==============================================  ============================================
  ``mean``      ȳ = Σ yᵢ / N                                    √(Σ sᵢ²) / N
  ``std``       s = √(Σ (yᵢ − ȳ)² / (N − 1))                    √(Σ ((yᵢ − ȳ) / ((N − 1) s))² sᵢ²)
  ``max``       max |yᵢ| (the peak error motion)                s_k at the position k of the peak
  ============  ==============================================  ============================================

For a campaign other than the reference, Δ = value − reference value and the combined standard
uncertainty u_c = √(u² + u_ref²). Two tests (:class:`DriftTolerance`):

- **absolute**: |Δ| > the absolute tolerance of the quantity's unit (µm or arcsec);
- **significance**: |Δ| > k·u_c (k = 2: a change that measurement noise explains with less than
  about 5 % probability).

``rule`` records which tests the change exceeds: ``abs+sig``, ``abs``, ``sig`` or ``within``, with
``(u unknown)`` when u_c is unknown (no significance test) and ``(no tolerance)`` when the unit has
no absolute tolerance (an effect parameter in its own unit: no absolute test); ``reference`` for
the reference campaign's own rows and ``unavailable`` when either value is missing
(unidentifiable). ``flagged`` applies the tolerance's ``require`` policy: ``both`` (default: large
enough to matter *and* not explained by noise; a test that cannot be made is left out, so the other
decides alone; never flagged when neither can be made), ``abs``, ``sig`` or ``either``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd

from tasks.analysis.compensation import requested_objective

PDGE_COMPONENTS = {"dx_um": ("dx", "um"), "dy_um": ("dy", "um"), "dz_um": ("dz", "um"),
                   "ex_arcsec": ("ex", "arcsec"), "ey_arcsec": ("ey", "arcsec"), "ez_arcsec": ("ez", "arcsec")}
PDGE_STATISTICS = ("mean", "std", "max")
SETUP_KINDS = ("mount",)  # pige-table kinds of the measurement setup (camera, plate fixtures), not of the machine
POLICIES = ("both", "abs", "sig", "either")
DRIFT_COLUMNS = ("campaign_id", "time", "quantity", "kind", "table", "value", "uncertainty", "unit",
                 "reference_campaign_id", "delta_from_reference", "combined_uncertainty", "z", "flagged", "rule")
QUANTITY_COLUMNS = ("campaign_id", "quantity", "kind", "table", "value", "uncertainty", "unit")


@dataclass(frozen=True)
class DriftTolerance:
    """When a quantity counts as drifted, and when the verification error calls for recompensation.

    abs_um, abs_arcsec: absolute tolerance on |Δ| for quantities in µm and in arcsec.
    k: coverage factor of the significance test |Δ| > k·u_c (u_c: combined standard uncertainty).
    require: which tests must be exceeded to flag: "both" (default), "abs", "sig" or "either".
    after_position_um, after_orientation_arcsec: the mean tip error after compensation over the
    validation poses (VBM measurement) above which the latest campaign's compensation is not good
    enough (the seed reached 1.80 µm and 52.9″). The orientation is the one the campaign's
    compensation aims at: the whole rotation, or the tool direction under ``tool-axis``.
    """

    abs_um: float = 5.0
    abs_arcsec: float = 15.0
    k: float = 2.0
    require: str = "both"
    after_position_um: float = 10.0
    after_orientation_arcsec: float = 100.0

    def __post_init__(self):
        if self.require not in POLICIES:
            raise ValueError(f"DriftTolerance.require must be one of {POLICIES}, not {self.require!r}")
        for name in ("abs_um", "abs_arcsec", "k", "after_position_um", "after_orientation_arcsec"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"DriftTolerance.{name} must be a positive number, not {value!r}")

    def absolute(self, unit: str) -> float:
        """The absolute tolerance for ``unit``: ``abs_um`` for "um", ``abs_arcsec`` for "arcsec",
        NaN for any other unit (an effect parameter's own unit: no absolute test)."""
        return {"um": self.abs_um, "arcsec": self.abs_arcsec}.get(unit, np.nan)

    def to_dict(self) -> dict:
        return asdict(self)


# --------------------------------------------------------------------------------------------
# Quantities
# --------------------------------------------------------------------------------------------


def _require(df: pd.DataFrame, columns, table: str) -> None:
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise ValueError(f"{table} table lacks the column(s) {', '.join(missing)}")


def pige_quantities(pige: pd.DataFrame) -> pd.DataFrame:
    """One row per campaign and ``pige`` table row (:data:`QUANTITY_COLUMNS`): quantity = the
    parameter's name, kind = its kind (pige, constant, squareness, mount, effect), value and
    uncertainty in its unit (µm or arcsec; an effect parameter's own unit); value and uncertainty
    NaN where ``identifiable`` is false."""
    if pige.empty:
        return pd.DataFrame(columns=list(QUANTITY_COLUMNS))
    _require(pige, ("campaign_id", "name", "kind", "unit", "value", "uncertainty", "identifiable"), "pige")
    identifiable = pige["identifiable"].fillna(False).astype(bool).to_numpy()
    value = pd.to_numeric(pige["value"], errors="coerce").to_numpy(dtype=float)
    unc = pd.to_numeric(pige["uncertainty"], errors="coerce").to_numpy(dtype=float)
    return pd.DataFrame({
        "campaign_id": pige["campaign_id"].astype(str).to_numpy(), "quantity": pige["name"].astype(str).to_numpy(),
        "kind": pige["kind"].astype(str).to_numpy(), "table": "pige",
        "value": np.where(identifiable, value, np.nan), "uncertainty": np.where(identifiable, unc, np.nan),
        "unit": pige["unit"].astype(str).to_numpy()})


def sweep_statistics(y: np.ndarray, s: np.ndarray) -> dict[str, tuple[float, float]]:
    """{"mean" | "std" | "max": (value, standard uncertainty)} of one PDGE component over a sweep.

    y: (N,) measured error motion at the N positions (µm or arcsec); s: (N,) their standard
    errors (same unit), taken as independent. Formulas in the module docstring; NaN values are
    dropped; "std" needs N ≥ 2 and its uncertainty is NaN when s = 0.
    """
    y, s = np.asarray(y, dtype=float), np.asarray(s, dtype=float)
    keep = np.isfinite(y)
    y, s = y[keep], s[keep]
    n = y.size
    if n == 0:
        return {name: (np.nan, np.nan) for name in PDGE_STATISTICS}
    mean = float(y.mean())
    u_mean = float(np.sqrt(np.sum(s**2)) / n)
    if n >= 2:
        dev = y - mean
        std = float(np.sqrt(np.sum(dev**2) / (n - 1)))
        u_std = float(np.sqrt(np.sum((dev / ((n - 1) * std)) ** 2 * s**2))) if std > 0 else np.nan
    else:
        std, u_std = np.nan, np.nan
    k = int(np.argmax(np.abs(y)))
    return {"mean": (mean, u_mean), "std": (std, u_std), "max": (float(abs(y[k])), float(s[k]))}


def pdge_quantities(pdge: pd.DataFrame) -> pd.DataFrame:
    """One row per campaign, axis, component and statistic (:data:`QUANTITY_COLUMNS`): quantity =
    ``"<axis>.<component>.<statistic>"`` (e.g. ``"X.dz.max"``), kind "pdge", value and uncertainty
    from :func:`sweep_statistics` of the measured column (e.g. ``dz_um``) and its ``std_dz_um``
    standard errors, unit "um" or "arcsec"."""
    if pdge.empty:
        return pd.DataFrame(columns=list(QUANTITY_COLUMNS))
    _require(pdge, ("campaign_id", "axis", *PDGE_COMPONENTS, *(f"std_{c}" for c in PDGE_COMPONENTS)), "pdge")
    rows = []
    for (campaign_id, axis), g in pdge.groupby(["campaign_id", "axis"], sort=False):
        for column, (component, unit) in PDGE_COMPONENTS.items():
            y = pd.to_numeric(g[column], errors="coerce").to_numpy(dtype=float)
            s = pd.to_numeric(g[f"std_{column}"], errors="coerce").to_numpy(dtype=float)
            for stat, (value, unc) in sweep_statistics(y, s).items():
                rows.append({"campaign_id": str(campaign_id), "quantity": f"{axis}.{component}.{stat}",
                             "kind": "pdge", "table": "pdge", "value": value, "uncertainty": unc, "unit": unit})
    return pd.DataFrame(rows, columns=list(QUANTITY_COLUMNS))


def campaign_times(images: pd.DataFrame) -> pd.Series:
    """Capture time of each campaign: its first image timestamp (UTC), indexed by campaign_id."""
    if images.empty:
        return pd.Series(dtype="datetime64[us, UTC]", name="time")
    _require(images, ("campaign_id", "timestamp"), "images")
    stamps = pd.to_datetime(images["timestamp"], utc=True, errors="coerce")
    return stamps.groupby(images["campaign_id"].astype(str)).min().rename("time")


# --------------------------------------------------------------------------------------------
# Flagging
# --------------------------------------------------------------------------------------------


def campaign_order(campaign_ids, times: pd.Series) -> list[str]:
    """Campaigns by capture time (then id); campaigns without a known time last."""
    ids = sorted(set(map(str, campaign_ids)))
    known = {c: times.get(c, pd.NaT) for c in ids}
    return sorted(ids, key=lambda c: (pd.isna(known[c]), known[c] if not pd.isna(known[c]) else 0, c))


def _rules(delta: np.ndarray, u_c: np.ndarray, tol: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray,
                                                                                    np.ndarray]:
    """(abs exceeded, sig exceeded, u known) per row; NaN deltas exceed nothing."""
    magnitude = np.abs(delta)
    with np.errstate(invalid="ignore"):
        above_abs = magnitude > tol
        known = np.isfinite(u_c)
        above_sig = known & (magnitude > k * np.where(known, u_c, np.inf))
    return above_abs, above_sig, known


def _rule_name(above_abs: bool, above_sig: bool, u_known: bool, tol_known: bool) -> str:
    """``abs+sig`` / ``abs`` / ``sig`` / ``within``, qualified by the tests that cannot be made."""
    name = {(True, True): "abs+sig", (True, False): "abs", (False, True): "sig"}.get((above_abs, above_sig), "within")
    missing = [text for text, ok in (("no tolerance", tol_known), ("u unknown", u_known)) if not ok]
    return f"{name} ({', '.join(missing)})" if missing else name


def flag_drift(quantities: pd.DataFrame, times: pd.Series, tolerance: DriftTolerance,
               reference: str | None = None) -> pd.DataFrame:
    """The drift table: every quantity of every campaign against the reference campaign.

    quantities: rows as :func:`pige_quantities` / :func:`pdge_quantities` (µm, arcsec).
    times: capture time per campaign_id (:func:`campaign_times`). reference: the reference
    campaign_id; default the earliest campaign. Returns :data:`DRIFT_COLUMNS`, campaigns in capture
    order: delta_from_reference = value − reference value, combined_uncertainty = √(u² + u_ref²),
    z = |Δ| / u_c, rule and flagged as in the module docstring. A quantity the reference lacks is
    "unavailable". Raises ValueError for an unknown reference campaign.
    """
    if quantities.empty:
        return pd.DataFrame(columns=list(DRIFT_COLUMNS))
    order = campaign_order(quantities["campaign_id"], times)
    reference = order[0] if reference is None else str(reference)
    if reference not in order:
        raise ValueError(f"reference campaign {reference!r} has no pige/pdge results (campaigns: {order})")
    q = quantities.copy()
    q["campaign_id"] = q["campaign_id"].astype(str)
    ref = q[q["campaign_id"] == reference].drop_duplicates("quantity").set_index("quantity")
    ref_value = q["quantity"].map(ref["value"]).to_numpy(dtype=float)
    ref_unc = q["quantity"].map(ref["uncertainty"]).to_numpy(dtype=float)
    value = q["value"].to_numpy(dtype=float)
    delta = value - ref_value
    u_c = np.sqrt(q["uncertainty"].to_numpy(dtype=float) ** 2 + ref_unc**2)
    tol = np.array([tolerance.absolute(u) for u in q["unit"].astype(str)])
    above_abs, above_sig, known = _rules(delta, u_c, tol, tolerance.k)
    available = np.isfinite(delta)
    is_ref = (q["campaign_id"] == reference).to_numpy()

    tol_known = np.isfinite(tol)
    rule = np.array([_rule_name(*flags) for flags in zip(above_abs, above_sig, known, tol_known, strict=True)],
                    dtype=object)
    rule = np.where(available, rule, "unavailable")
    rule = np.where(is_ref, "reference", rule)
    policy = {"both": (above_abs | ~tol_known) & (above_sig | ~known) & (tol_known | known),
              "abs": above_abs, "sig": above_sig, "either": above_abs | above_sig}[tolerance.require]
    flagged = policy & available & ~is_ref

    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.abs(delta) / u_c
    q["time"] = pd.to_datetime(q["campaign_id"].map(times), utc=True).astype("datetime64[us, UTC]")
    q["reference_campaign_id"] = reference
    q["delta_from_reference"] = np.where(is_ref, 0.0, delta)
    q["combined_uncertainty"] = u_c
    q["z"] = np.where(is_ref, 0.0, z)
    q["flagged"] = flagged
    q["rule"] = rule
    rank = {c: i for i, c in enumerate(order)}
    q = q.assign(_rank=q["campaign_id"].map(rank)).sort_values(["_rank"], kind="stable").drop(columns="_rank")
    return q[list(DRIFT_COLUMNS)].reset_index(drop=True)


def drift_table(pige: pd.DataFrame, pdge: pd.DataFrame, images: pd.DataFrame, tolerance: DriftTolerance,
                reference: str | None = None) -> pd.DataFrame:
    """:func:`flag_drift` of the PIGE and PDGE quantities of every campaign in the lake tables."""
    quantities = pd.concat([pige_quantities(pige), pdge_quantities(pdge)], ignore_index=True)
    return flag_drift(quantities, campaign_times(images), tolerance, reference)


# --------------------------------------------------------------------------------------------
# Verification and verdict
# --------------------------------------------------------------------------------------------


def campaign_objectives(compensation: pd.DataFrame) -> pd.Series:
    """The orientation objective each campaign was compensated with (``campaign_id`` → "full" or
    "tool-axis"), from the ``compensation`` table's per-pose ``orientation_objective``: "tool-axis"
    when any pose was asked for it (a pose that fell back says so in its label), "full" otherwise,
    also for partitions written before the column existed."""
    if compensation.empty or "campaign_id" not in compensation:
        return pd.Series(dtype=object, name="orientation_objective")
    labels = compensation.get("orientation_objective", pd.Series("full", index=compensation.index)).fillna("full")
    return labels.groupby(compensation["campaign_id"].astype(str)).agg(requested_objective).rename(
        "orientation_objective")


def verification_summary(verification: pd.DataFrame, compensation: pd.DataFrame | None = None) -> pd.DataFrame:
    """Mean tip error per campaign, phase (before/after) and source (vbm/truth) over the validation
    poses: columns campaign_id, phase, source, n, position_um, position_sem_um,
    orientation_arcsec, orientation_sem_arcsec, tool_direction_arcsec, tool_direction_sem_arcsec
    (sem: standard error of the mean, ddof = 1; tool direction NaN for partitions without it),
    orientation_objective (:func:`campaign_objectives` of ``compensation``; "full" without it) and
    objective_orientation_arcsec / _sem_arcsec: the orientation error the campaign's compensation
    aims at, the whole rotation for "full", the tool direction for "tool-axis"."""
    columns = ["campaign_id", "phase", "source", "n", "position_um", "position_sem_um", "orientation_arcsec",
               "orientation_sem_arcsec", "tool_direction_arcsec", "tool_direction_sem_arcsec",
               "orientation_objective", "objective_orientation_arcsec", "objective_orientation_sem_arcsec"]
    if verification.empty:
        return pd.DataFrame(columns=columns)
    _require(verification, ("campaign_id", "phase", "source", "position_um", "orientation_arcsec"), "verification")
    v = verification.assign(campaign_id=verification["campaign_id"].astype(str))
    if "tool_direction_arcsec" not in v:
        v = v.assign(tool_direction_arcsec=np.nan)
    v["tool_direction_arcsec"] = v["tool_direction_arcsec"].astype(float)
    g = v.groupby(["campaign_id", "phase", "source"])
    out = pd.DataFrame({"n": g["position_um"].count(),
                        "position_um": g["position_um"].mean(), "position_sem_um": g["position_um"].sem(),
                        "orientation_arcsec": g["orientation_arcsec"].mean(),
                        "orientation_sem_arcsec": g["orientation_arcsec"].sem(),
                        "tool_direction_arcsec": g["tool_direction_arcsec"].mean(),
                        "tool_direction_sem_arcsec": g["tool_direction_arcsec"].sem()}).reset_index()
    objectives = campaign_objectives(compensation if compensation is not None else pd.DataFrame())
    out["orientation_objective"] = [objectives.get(c, "full") for c in out["campaign_id"]]
    tool_axis = out["orientation_objective"].eq("tool-axis")
    for value in ("", "_sem"):
        out[f"objective_orientation{value}_arcsec"] = out[f"orientation{value}_arcsec"].where(
            ~tool_axis, out[f"tool_direction{value}_arcsec"])
    return out[columns]


@dataclass(frozen=True)
class Verdict:
    """Whether the machine needs recompensation, with the reasons in words (Markdown)."""

    needs_recompensation: bool
    latest_campaign_id: str | None
    reference_campaign_id: str | None
    reasons: tuple[str, ...]
    notes: tuple[str, ...]

    def text(self) -> str:
        """The verdict as a Markdown paragraph and bullet list."""
        if self.latest_campaign_id is None:
            return "**No verdict:** no calibrated campaign in the results lake."
        head = ("**Recompensate the machine.**" if self.needs_recompensation else
                "**No recompensation needed.**")
        head += (f" Latest campaign `{self.latest_campaign_id}` against reference "
                 f"`{self.reference_campaign_id}`.")
        lines = [f"- {r}" for r in self.reasons] + [f"- {n}" for n in self.notes]
        return head + ("\n\n" + "\n".join(lines) if lines else "")


def _describe(rows: pd.DataFrame, limit: int = 8) -> str:
    from tasks.core.units import UNIT_LABEL

    parts = [f"{r.quantity} {r.delta_from_reference:+.2f} {UNIT_LABEL.get(r.unit, r.unit)} (z = {r.z:.1f})"
             for r in rows.sort_values("z", ascending=False).head(limit).itertuples()]
    more = f" and {len(rows) - limit} more" if len(rows) > limit else ""
    return ", ".join(parts) + more


def verdict(drift: pd.DataFrame, verification: pd.DataFrame, tolerance: DriftTolerance) -> Verdict:
    """Does the machine need recompensation? Judged on the latest campaign (by capture time).

    drift: :func:`flag_drift` output; verification: :func:`verification_summary` output. Yes when
    the latest campaign has a flagged machine quantity (a ``pige`` table parameter of any kind but
    :data:`SETUP_KINDS` — PIGEs, constants, squareness — or a PDGE statistic: the compensation
    computed at the reference no longer describes the machine), or when its mean VBM-measured
    tip error after its own compensation exceeds ``tolerance.after_position_um`` or
    ``after_orientation_arcsec`` (the identified model does not compensate the machine well
    enough). The orientation judged is the one the campaign's compensation aims at
    (``objective_orientation_arcsec``): the whole rotation, or the tool direction for a campaign
    compensated with ``--orientation tool-axis``. A flagged mount parameter (camera or plate
    fixture) is a note, not a reason.
    """
    if drift.empty:
        return Verdict(False, None, None, (), ())
    latest = str(drift["campaign_id"].iloc[-1])
    reference = str(drift["reference_campaign_id"].iloc[0])
    rows = drift[drift["campaign_id"] == latest]
    reasons, notes = [], []
    if latest == reference:
        notes.append("Only the reference campaign is calibrated: no drift to judge yet.")
    machine = rows[rows["flagged"] & (rows["table"] == "pige") & ~rows["kind"].isin(SETUP_KINDS)]
    pdge = rows[rows["flagged"] & (rows["kind"] == "pdge")]
    mount = rows[rows["flagged"] & (rows["table"] == "pige") & rows["kind"].isin(SETUP_KINDS)]
    if len(machine):
        reasons.append(f"{len(machine)} PIGE parameter(s) moved past tolerance: {_describe(machine)}.")
    if len(pdge):
        reasons.append(f"{len(pdge)} PDGE statistic(s) moved past tolerance: {_describe(pdge)}.")
    if len(mount):
        notes.append(f"Mount parameter(s) of the measurement setup (camera or plate) moved: {_describe(mount)} — "
                     "check the fixtures; not an error of the machine.")
    unavailable = int((rows["rule"] == "unavailable").sum())
    if unavailable and latest != reference:
        notes.append(f"{unavailable} quantity(ies) could not be compared (unidentifiable in this or the "
                     f"reference campaign).")
    after = verification[(verification["campaign_id"].astype(str) == latest) & (verification["phase"] == "after")
                         & (verification["source"] == "vbm")] if not verification.empty else verification
    if after.empty:
        notes.append("No after-compensation capture for this campaign: compensation quality not judged.")
    else:
        a = after.iloc[0]
        tool_axis = a.orientation_objective == "tool-axis"
        orientation = a.objective_orientation_arcsec
        # NaN (a tool-axis partition without the column) must not pass as "within"
        past = (a.position_um > tolerance.after_position_um
                or not orientation <= tolerance.after_orientation_arcsec)
        measure = ("of tool direction (compensated for the tool axis; the rotation about it is left free)"
                   if tool_axis else "of orientation")
        stated = (f"{orientation:.1f} arcsec {measure}" if np.isfinite(orientation) else
                  f"no figure {measure} (a verification table without it)")
        sentence = (f"Mean tip error after compensation (VBM, {int(a.n)} validation poses): {a.position_um:.2f} µm "
                    f"and {stated} (threshold {tolerance.after_position_um:g} µm, "
                    f"{tolerance.after_orientation_arcsec:g} arcsec)")
        (reasons if past else notes).append(sentence + (": past the threshold." if past else ": within."))
    if not reasons and latest != reference:
        notes.insert(0, "No PIGE or PDGE quantity moved past tolerance.")
    return Verdict(bool(reasons), latest, reference, tuple(reasons), tuple(notes))

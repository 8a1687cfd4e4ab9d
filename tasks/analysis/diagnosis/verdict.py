"""The diagnosis in words.

The verdict names the camera whose residual was examined, the direction in which the explained
part is largest relative to the pose noise (camera axes mapped to the machine's, translation
"along" or rotation "about"), what the candidate follows, its spec with the fitted amplitudes,
the share of the residual sum of squares it explains, and its significance:

    camera1 residual along Y follows X with a 2.5 mm period: `pitch_cyclic:axis=X,period_mm=2.5,...`
    explains 69 % of it (p < 1e-9, ΔBIC −3907; cross-validated RMS 4.71 → 2.62)

A user family may describe what it follows with a class attribute ``follows``, a format string
over its parameter values (e.g. ``"time with a {period_s} s period"``).
"""

from __future__ import annotations

import numpy as np
from scipy.stats import false_discovery_control

from tasks.analysis.diagnosis.candidates import Candidate
from tasks.analysis.diagnosis.linearisation import Linearisation
from tasks.analysis.residual_trends import ALPHA
from tasks.machine.kinematics import forward

ORDINALS = {1: "1st", 2: "2nd", 3: "3rd"}


def follows(cand: Candidate) -> str:
    """What the candidate's signature follows, in words."""
    v = cand.values
    axis = cand.axis
    own = getattr(cand.cls, "follows", None)
    if isinstance(own, str):
        return own.format(**{k: (f"{x:.4g}" if isinstance(x, float) else x) for k, x in v.items()})
    if cand.scanned:
        name, period = next(iter(cand.scanned.items()))
        unit = next(p.unit for p in cand.cls.params if p.name == name)
        var = "time" if cand.period_variable == "time" else cand.period_variable
        return f"{var} with a {period:.3g} {unit} period"
    fam = cand.family
    if fam == "backlash":
        return f"the approach direction of {axis}"
    if fam == "thermal_drift":
        return "time" if v.get("driver") == "time" else "temperature"
    if hasattr(cand.cls, "harmonic"):
        h = int(cand.cls.harmonic)
        return f"{axis} at the {ORDINALS.get(h, f'{h}th')} harmonic"
    if fam == "gravity_sag":
        return f"1 − cos {axis}"
    if fam == "scale":
        return f"{axis} linearly"
    if fam == "focal_drift":
        return f"{v.get('axis')} through {v.get('camera')}'s focal length"
    if fam == "lens_distortion":
        return f"the plate's position in {v.get('camera')}'s image"
    if fam == "tool_offset":
        return "nothing a camera sees"
    return axis or fam


def residual_direction(lin: Linearisation, fitted: np.ndarray) -> str:
    """"along Y" / "about X": the machine direction in which the whitened explained part ``fitted``
    (M,) is largest, taken in the camera frame (camera 1 rides on the linear axes and does not turn)."""
    n = lin.n_images
    f = np.linalg.solve(lin.W, fitted.reshape(n, 6)[..., None])[..., 0]  # unwhitened, plate frame
    R = lin.ident.T[:, :3, :3]  # plate -> camera
    cam = np.concatenate([np.einsum("nij,nj->ni", R, f[:, :3]), np.einsum("nij,nj->ni", R, f[:, 3:])], axis=1)
    cov = lin.ident.cov
    std = np.concatenate([np.sqrt(np.einsum("nij,njk,nik->ni", R, cov[:, :3, :3], R)),
                          np.sqrt(np.einsum("nij,njk,nik->ni", R, cov[:, 3:, 3:], R))], axis=1)
    energy = np.sum((cam / std) ** 2, axis=0)
    k = int(np.argmax(energy))
    camera = str(lin.ident.table.camera.iloc[0])
    R_home = forward(lin.machine, np.zeros((1, 5))).pose(camera)[0, :3, :3]  # camera axes in the base frame
    machine_axis = "XYZ"[int(np.argmax(np.abs(R_home[:, k % 3])))]
    return f"{'along' if k < 3 else 'about'} {machine_axis}"


def p_text(p: float) -> str:
    return "p < 1e-9" if p < 1e-9 else f"p = {p:.2g}"


def explained_sentence(camera: str, direction: str, cand: Candidate, spec: str, explained: float, p: float,
                       delta_bic: float, cv_before: float, cv_after: float) -> str:
    cv = "" if not np.isfinite(cv_after) else f"; cross-validated RMS {cv_before:.2f} → {cv_after:.2f}"
    return (f"{camera} residual {direction} follows {follows(cand)}: `{spec}` explains {100 * explained:.0f} % "
            f"of it ({p_text(p)}, ΔBIC {delta_bic:+.0f}{cv})")


def residual_follows_sentence(trends, camera: str, limit: int = 5) -> str | None:
    """When no candidate is accepted: the variables ``camera``'s residual follows, from the trend tests
    of :func:`tasks.analysis.residual_trends.trend_tests` (``trends``, the ``residual_trends`` table). A panel
    counts when it survives the Benjamini–Hochberg false-discovery control at :data:`ALPHA` over all of
    the camera's panels (one in twenty of them is flagged at 5 % by chance alone on a campaign that
    lacks nothing); those are named smallest p-value first, one per variable, at most ``limit``, each
    with its component and the span of its bin means (µm or arcsec). When panels are flagged at 5 % but
    none survives, the sentence says the residual follows nothing beyond chance. None when no panel is
    flagged. What the residual follows is where an effect of one's own would act (docs/user-effects.md)."""
    mine = trends[(trends["camera"] == camera) & np.isfinite(trends["p_value"].astype(float))]
    flagged = int(mine["significant"].sum())
    if not flagged:
        return None
    q = false_discovery_control(mine["p_value"].to_numpy(float))
    t = mine[q <= ALPHA]
    counts = (f"{flagged} of its {len(mine)} trend tests flagged at {ALPHA:.0%}, chance alone flags about "
              f"{ALPHA * len(mine):.0f}")
    if t.empty:
        return (f"The {camera} residual follows no variable beyond noise ({counts}; none survives the "
                f"false-discovery control over the tests).")
    t = t.sort_values(["p_value", "statistic"], ascending=[True, False], kind="stable")
    top = t.drop_duplicates("variable").head(limit)
    parts = [f"{r.variable} ({r.component} spans {r.span:.3g} {r.component.rsplit('_', 1)[-1]}, "
             f"{p_text(r.p_value)})" for r in top.itertuples(index=False)]
    return (f"What the {camera} residual follows most ({counts}; {len(t)} survive the false-discovery control): "
            f"{'; '.join(parts)}. An effect that depends on these and that no catalogue family describes can be "
            f"written as a family of one's own (docs/user-effects.md).")

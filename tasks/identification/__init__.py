"""Identification of the machine's geometric errors from measured plate poses (§3.3, §4.2).

- :mod:`.measurements` joins the images table (commands, stage, time) with the measured poses.
- :mod:`.pdge_extraction` measures each axis' six error motions from its single-axis sweep
  (eqs. 13–19) and fits smooth profiles referred to home.
- :mod:`.squareness` computes the squareness of the linear axes from their motion directions (eq. 21).
- :mod:`.parameters` names the constant parameters the fit identifies and applies them to a model.
- :mod:`.levenberg_marquardt` is the damped Gauss–Newton solver of eq. 22 with SVD diagnostics.
- :mod:`.pige_identification` stacks the pose residuals of eq. 20 and runs the fit.
"""

"""Identification of the machine's geometric errors from measured plate poses (§3.3, §4.2).

- :mod:`.measurements` joins the images table (commands, stage, time) with the measured poses.
- :mod:`.pdge_extraction` measures each axis' six error motions from its single-axis sweep
  (eqs. 13–19) and fits smooth profiles referred to home.
- :mod:`.smoothing` is the PDGE profiles' smoothing spline with its GCV-chosen roughness.
- :mod:`.parameters` names the constant parameters the fit identifies (the squareness of the linear
  axes of eq. 21 among them) and applies them to a model.
- :mod:`.levenberg_marquardt` is the damped Gauss–Newton solver of eq. 22 with SVD diagnostics.
- :mod:`.pige_identification` stacks the pose residuals of eq. 20 and runs the fit.
- :mod:`.uncertainty` propagates the camera intrinsics and the pose noise into the parameters.
"""

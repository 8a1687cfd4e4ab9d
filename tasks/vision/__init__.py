"""From images to plate poses: dot-grid detection, camera models and self-calibration, PnP with pose covariances."""

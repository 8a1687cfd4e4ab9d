"""Units fivecal computes in (mm, rad) and reports in (µm, arcsec), and their labels."""

from __future__ import annotations

import numpy as np

ARCSEC = np.pi / (180.0 * 3600.0)  # rad per arcsec
UM = 1e-3  # mm per µm
RAD_TO_ARCSEC = 180.0 / np.pi * 3600.0  # arcsec per rad
UNIT_LABEL = {"um": "µm", "arcsec": "arcsec", "mm": "mm", "deg": "deg"}  # column suffix → printed unit

# The largest uncertainty a fit reports (µm, arcsec or steps of an effect's parameter): beyond it a
# parameter is declared unidentifiable rather than given a number no one should read.
MAX_UNCERTAINTY = 50.0

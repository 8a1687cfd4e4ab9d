"""fivecal: vision-based calibration of a five-axis precision dispensing machine."""

import fivecal.prefect_defaults  # noqa: F401  (before anything imports Prefect)
from tasks.core.version import FIVECAL_VERSION as __version__

__all__ = ["__version__"]

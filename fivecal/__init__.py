"""fivecal: vision-based calibration of a five-axis precision dispensing machine."""

from tasks.core.version import FIVECAL_VERSION as __version__

__all__ = ["__version__"]

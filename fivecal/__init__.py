"""fivecal: vision-based calibration of a five-axis precision dispensing machine."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("fivecal")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+source"

"""dm2: refine SLAM trajectories with DeepMapping2."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("dm2")
except PackageNotFoundError:  # running from a source tree without install
    __version__ = "0.0.0+unknown"

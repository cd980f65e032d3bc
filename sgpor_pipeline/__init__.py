"""sgpor-pipeline: remove an object from a photographed 3D scene with Gaussian Splatting."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("sgpor-pipeline")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

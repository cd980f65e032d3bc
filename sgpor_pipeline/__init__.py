"""sgpor-pipeline: remove an object from a photographed 3D scene with Gaussian Splatting."""

import os
from importlib.metadata import PackageNotFoundError, version

# Two OpenMP runtimes share the cores (torch's and our kernel's): threads that spin while idle would
# starve the other runtime's work. Passive waiting, unless the user chose otherwise; set before
# torch is imported through us (see gaussians/_raster_cpu.py).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

try:
    __version__ = version("sgpor-pipeline")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

"""sgpor-pipeline: remove an object from a photographed 3D scene with Gaussian Splatting."""

import os
import sys
from importlib.metadata import PackageNotFoundError, version

# pycolmap's wheel carries its own zlib; loaded before OpenCV, it serves OpenCV's PNG writer, which
# then aborts the process ("double free or corruption" in deflateEnd, pycolmap 4.2 with
# opencv-python 5.0) at the first PNG written. Loading cv2 first is enough; after pycolmap it is too
# late (also when cv2 came after it), so say so instead of crashing mid-run.
_loaded = list(sys.modules)  # in import order
if "pycolmap" in sys.modules and ("cv2" not in sys.modules or _loaded.index("pycolmap") < _loaded.index("cv2")):
    raise ImportError("sgpor_pipeline must be imported before pycolmap (or import cv2 first): pycolmap's "
                      "bundled zlib, loaded first, makes OpenCV's PNG writer abort the process. Move "
                      "'import sgpor_pipeline' (or 'import cv2') above 'import pycolmap'")
del _loaded
import cv2  # noqa: E402, F401  (loaded here, before any pycolmap import of ours: see above)

# Two OpenMP runtimes share the cores (torch's and our kernel's): threads that spin while idle would
# starve the other runtime's work. Passive waiting, unless the user chose otherwise; set before
# torch is imported through us (see gaussians/_raster_cpu.py).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

try:
    __version__ = version("sgpor-pipeline")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

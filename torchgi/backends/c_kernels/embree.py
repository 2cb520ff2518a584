"""The embree 4 library that embreex ships (else one the system has), found and opened by ctypes
for the compiled path tracer: no embree headers, no link step."""

from __future__ import annotations

import ctypes
import ctypes.util
import glob
import os

from torchgi.backends.base import mark_embree_started
from torchgi.core.check import require

__all__ = ["EMBREE_FUNCTIONS", "embree_functions"]

# the embree 4 entry points the compiled path tracer calls, in the order it takes them
EMBREE_FUNCTIONS = ("rtcNewDevice", "rtcNewScene", "rtcNewGeometry", "rtcSetNewGeometryBuffer", "rtcCommitGeometry",
                    "rtcAttachGeometry", "rtcReleaseGeometry", "rtcCommitScene", "rtcReleaseScene",
                    "rtcReleaseDevice", "rtcIntersect1", "rtcOccluded1", "rtcGetDeviceError")


def embree_functions() -> list[int]:
    """Addresses of :data:`EMBREE_FUNCTIONS` in the embree 4 library that embreex ships (else one
    the system has), for the compiled path tracer; marks embree as started in this process (its
    BVH builds start TBB threads). Raises ``RuntimeError`` naming what is missing.

    Example:
        >>> len(embree_functions()) == len(EMBREE_FUNCTIONS)
        True
    """
    embreex = require("embreex", "render")
    root = os.path.dirname(os.path.dirname(os.path.abspath(embreex.__file__)))
    found = sorted(glob.glob(os.path.join(root, "embreex.libs", "libembree4*"))
                   + glob.glob(os.path.join(root, "embreex", ".dylibs", "libembree4*")))
    path = found[0] if found else ctypes.util.find_library("embree4")
    if path is None:
        raise RuntimeError("no embree 4 library found beside embreex or on the system")
    lib = ctypes.CDLL(path)
    missing = [name for name in EMBREE_FUNCTIONS if not hasattr(lib, name)]
    if missing:
        raise RuntimeError(f"{path} lacks {', '.join(missing)}")
    mark_embree_started()
    return [ctypes.cast(getattr(lib, name), ctypes.c_void_p).value for name in EMBREE_FUNCTIONS]

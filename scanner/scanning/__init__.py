"""Scanning: laser stripes to a stitched point cloud in the robot base frame (mm).

Modules, in the order the data flows:

``stripe``       :func:`extract_stripe` -> :class:`StripeProfile` (sub-pixel centres per frame)
``triangulate``  :class:`Triangulator`, :func:`triangulate_frame` (pixels -> light plane -> base)
``stitch``       :func:`build_cloud`, :func:`filter_cloud`, :func:`refine_sweeps` (ICP)
``cloud_io``     :func:`write_cloud`, :func:`read_cloud` (PLY, PCD, E57, with provenance)
``pipeline``     :func:`scan_session`, :class:`ScanOptions`, :class:`ScanResult`
``synthetic``    analytic stripe frames and a table-and-block sweep with exact truth

Names are importable from this package directly; the modules that need Open3D load it only
when one of their names is first used, so stripe extraction in a worker stays light.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "StripeFlag": "stripe",
    "StripeOptions": "stripe",
    "StripeProfile": "stripe",
    "extract_stripe": "stripe",
    "orientation_from_calibration": "stripe",
    "orientation_from_image": "stripe",
    "Triangulator": "triangulate",
    "triangulate_frame": "triangulate",
    "build_cloud": "stitch",
    "filter_cloud": "stitch",
    "refine_sweeps": "stitch",
    "SweepCorrection": "stitch",
    "read_cloud": "cloud_io",
    "write_cloud": "cloud_io",
    "ScanOptions": "pipeline",
    "ScanResult": "pipeline",
    "scan_session": "pipeline",
    "check_scan_inputs": "pipeline",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)

"""Scanning: stripe profiles to a stitched point cloud in the robot base frame (mm).

Modules, in the order the data flows:

``triangulate``  :class:`Triangulator`, :func:`triangulate_frame` (pixels -> light plane -> base)
``stitch``       :func:`build_cloud`, :func:`filter_cloud`, :func:`refine_sweeps` (ICP)
``pipeline``     :func:`scan_session`, :class:`ScanOptions`, :class:`ScanResult`

The profiles come from :mod:`scanner.stripe`; clouds are written by :mod:`scanner.formats.clouds`.
"""

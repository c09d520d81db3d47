"""Scanning: stripe profiles to a stitched point cloud in the robot base frame (mm).

Modules, in the order the data flows:

``triangulate``  :class:`Triangulator`, :func:`triangulate_frame` (pixels -> light plane -> base)
``stitch``       :func:`build_cloud`, :func:`filter_cloud`, :func:`refine_sweeps` (ICP)
``pipeline``     :func:`scan_session`, :class:`ScanOptions`, :class:`ScanResult`
``coverage``     :func:`sweep_coverage`, :func:`visible_from_above` (what a sweep measures)
``planning``     :func:`plan_sweeps` (sweeps that cover a part, from its mesh)

The profiles come from :mod:`scanner.stripe`; clouds are written by :mod:`scanner.formats.clouds`.
"""

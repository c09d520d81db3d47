"""Calibration: target detection, intrinsics, light plane, extrinsics and hand-eye."""

"""Robot laser-line scanner: capture sessions, the virtual cell, scanning and the PLC service.

Package map (the data flows top to bottom; each stage reads and writes artefacts on disk):

- ``scanner.conventions``      frames, ``a_from_b`` transforms, units, robot pose conventions
- ``scanner.session``          capture-session folders (``scan-session/1``)
- ``scanner.calibration_file`` the calibration file (``scan-calibration/1``)
- ``scanner.virtual_cell``     the simulator that stands in for robot, camera and laser
- ``calibration``              target detection, intrinsics, light plane, extrinsics, hand-eye
- ``scanner.scanning``         stripe extraction, triangulation, sweep stitching
- ``metrology``                feature fits, inspection plans, EF check, acceptance reports
- ``scanner.plc``              the Modbus TCP service for the PLC
- ``scanner.cli``              the ``scanner`` command
"""

__version__ = "0.1.0"

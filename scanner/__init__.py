"""Robot laser-line scanner: capture sessions, the virtual cell, scanning and the PLC service.

Package map (the data flows top to bottom; each stage reads and writes artefacts on disk):

- ``scanner.core.conventions``      frames, ``a_from_b`` transforms, units, robot pose conventions
- ``scanner.formats.session``          capture-session folders (``scan-session/1``)
- ``scanner.formats.calibration_file`` the calibration file (``scan-calibration/1``)
- ``scanner.virtual_cell``     the simulator that stands in for robot, camera and laser
- ``calibration``              target detection, intrinsics, light plane, extrinsics, hand-eye
- ``scanner.scanning``         stripe extraction, triangulation, sweep stitching
- ``metrology``                feature fits, inspection plans, EF check, acceptance reports
- ``scanner.app.plc``              the Modbus TCP service for the PLC
- ``scanner.app.cli``              the ``scanner`` command
"""

__version__ = "0.1.0"

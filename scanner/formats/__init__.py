"""File formats: capture sessions, the calibration file, clouds, HTML building blocks, job-folder layout."""

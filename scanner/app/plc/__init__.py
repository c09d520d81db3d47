"""The PLC service: Modbus TCP server, handshake and job runner, SQLite job history.

``scanner serve`` runs :func:`scanner.app.plc.service.serve`; the register map and error codes
live in :mod:`scanner.app.plc.registers`, the framing in :mod:`scanner.app.plc.modbus`, the network
guards in :mod:`scanner.app.plc.server`, the jobs in :mod:`scanner.app.plc.jobs` and the history in
:mod:`scanner.app.plc.history`. See docs/PLC.md.
"""

from scanner.app.plc.config import PlcConfig, load_plc_config
from scanner.app.plc.history import JobHistory, JobRecord
from scanner.app.plc.jobs import JobContext, JobError, JobOutcome, JobRunner, PipelineJobs
from scanner.app.plc.registers import Command, ErrorCode, State, Status, format_register_map

__all__ = [
    "Command",
    "ErrorCode",
    "JobContext",
    "JobError",
    "JobHistory",
    "JobOutcome",
    "JobRecord",
    "JobRunner",
    "PipelineJobs",
    "PlcConfig",
    "State",
    "Status",
    "format_register_map",
    "load_plc_config",
]

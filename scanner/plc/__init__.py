"""The PLC service: Modbus TCP server, handshake and job runner, SQLite job history.

``scanner serve`` runs :func:`scanner.plc.service.serve`; the register map and error codes
live in :mod:`scanner.plc.registers`, the framing in :mod:`scanner.plc.modbus`, the network
guards in :mod:`scanner.plc.server`, the jobs in :mod:`scanner.plc.jobs` and the history in
:mod:`scanner.plc.history`. See docs/PLC.md.
"""

from scanner.plc.config import PlcConfig, load_plc_config
from scanner.plc.history import JobHistory, JobRecord
from scanner.plc.jobs import JobContext, JobError, JobOutcome, JobRunner, PipelineJobs
from scanner.plc.registers import Command, ErrorCode, State, Status, format_register_map

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

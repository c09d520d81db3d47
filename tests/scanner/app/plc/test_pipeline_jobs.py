"""Every PLC command end to end on the real stages, as shipped: a fresh service with the default
config (process worker, virtual-cell source), driven over Modbus TCP from command to DONE.

Only what a test must change is changed: a free loopback port and storage under a temporary
folder. The PLC heartbeat is beaten by a thread, as a PLC would, so the watchdog stays armed.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from scanner.app.plc.config import PlcConfig, load_plc_config
from scanner.app.plc.history import JobHistory
from scanner.app.plc.registers import ErrorCode, Status
from tests.scanner.app.plc.conftest import running_service
from tests.scanner.app.plc.test_service import Plc, done

pytestmark = [pytest.mark.slow, pytest.mark.timeout(1500)]


def _shipped_config(tmp: Path) -> PlcConfig:
    config = load_plc_config()  # configs/plc.toml, as a user gets it
    assert config.jobs.worker == "process" and config.jobs.runner == "pipeline"
    assert config.source.kind == "virtual"
    return replace(
        config,
        server=replace(config.server, port=0),
        storage=replace(
            config.storage,
            history_db=str(tmp / "history.sqlite"),
            work_dir=str(tmp / "jobs"),
            calibration=str(tmp / "calibration.json"),
        ),
    )


@pytest.fixture
def plc_and_config(tmp_path: Path) -> Iterator[tuple[Plc, PlcConfig]]:
    config = _shipped_config(tmp_path)
    with running_service(config, None) as svc:  # type: ignore[arg-type]
        plc, beat = Plc(svc.port), Plc(svc.port)
        stop = threading.Event()

        def heartbeat() -> None:
            n = 0
            while not stop.wait(1.0):
                n = (n + 1) % 65536
                beat.write(2, [n])

        thread = threading.Thread(target=heartbeat, daemon=True)
        thread.start()
        try:
            yield plc, config
        finally:
            stop.set()
            thread.join(5.0)
            plc.close()
            beat.close()


def _run(plc: Plc, command: int, sequence: int, parameter: int = 0) -> dict[str, int]:
    assert plc.wait(lambda s: bool(s["bits"] & Status.READY) and not s["bits"] & Status.BUSY)
    assert plc.write(0, [command, sequence, 0, parameter]) == 0
    status = plc.wait(lambda s: s["ack"] == sequence and done(s), timeout=1400)
    assert plc.write(0, [0]) == 0
    return status


def test_every_plc_command_runs_the_real_stages(plc_and_config):
    plc, config = plc_and_config
    calibration = Path(config.storage.calibration)

    # 1 before any calibration: a recorded error, then 4 clears it.
    st = _run(plc, 1, 1)
    assert st["bits"] & Status.ERROR and st["error"] == ErrorCode.NO_CALIBRATION
    st = _run(plc, 4, 2)
    assert not st["bits"] & Status.ERROR

    # 3: full calibration on a fresh virtual capture, through the process worker whose stages
    # open their own pools; it passes the gate and is installed.
    st = _run(plc, 3, 3)
    assert st["bits"] & Status.DONE and st["bits"] & Status.PASS, st
    assert st["error"] == ErrorCode.NONE
    assert st["bits"] & Status.CALIBRATED
    installed = json.loads(calibration.read_text("utf-8"))
    assert installed["format"] == "scan-calibration/1"
    assert installed["quality"]["provenance"]["stage"] == "calibrate"
    plane_um = st["r1"]
    assert 0 < plane_um < config.calibration_gate.max_light_plane_rms_um

    # 1: the recalibration check with that calibration: the EF error within tolerance.
    st = _run(plc, 1, 4)
    assert st["bits"] & Status.DONE and st["bits"] & Status.RESULT_VALID, st
    assert st["bits"] & Status.PASS
    assert 0 <= st["r1"] <= st["r2"] <= config.check.max_abs_um
    assert 0 <= st["r3"] <= config.check.max_o_spread_um

    # 2: a scan job of recipe 1 (a sweep of more than 32 frames: several extraction chunks).
    st = _run(plc, 2, 5, parameter=1)
    assert st["bits"] & Status.DONE and st["bits"] & Status.RESULT_VALID, st
    assert st["error"] == ErrorCode.NONE

    with JobHistory(config.storage.history_db) as history:
        jobs = {j.command: j for j in reversed(history.latest(10))}  # the newest of each
    check_job, scan_job = jobs[1], jobs[2]
    check_dir = Path(check_job.report_path).parent
    assert (check_dir / "check.json").is_file() and (check_dir / "check.html").is_file()
    scan_dir = Path(scan_job.report_path).parent
    for name in ("cloud.ply", "measure.json", "measure.csv", "measure.html"):
        assert (scan_dir / name).is_file(), name
    measured = json.loads((scan_dir / "measure.json").read_text("utf-8"))
    assert measured["summary"]["failed"] == 0, measured["summary"]["line"]

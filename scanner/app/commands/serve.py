"""`scanner serve`: the Modbus TCP service a PLC drives (docs/PLC.md).

Runs until SIGTERM or Ctrl-C. ``--print-map`` prints the register map and error codes and
exits. ``--port 0`` picks a free port; the line ``listening on HOST:PORT`` says which.

Bad input is refused before the service listens, with one line and exit 2: a ``--host`` that
is not an IP address or host name, a ``[jobs] runner`` whose module does not exist (the line
names the config file), a ``storage.history_db`` that is not a job history or cannot be
created (the line names that file).
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path

from scanner.app.plc.config import check_host, load_plc_config
from scanner.app.plc.registers import format_register_map
from scanner.app.plc.service import serve
from scanner.app.plc.worker import check_runner
from scanner.core.config import resolve_config
from scanner.core.fileio import InputError

SUMMARY = "run the Modbus TCP service for a PLC"
DESCRIPTION = "Run the Modbus TCP service for a PLC until SIGTERM or Ctrl-C."


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help=SUMMARY, description=DESCRIPTION)
    p.add_argument("--config", default=None, help="PLC service config (default configs/plc.toml)")
    p.add_argument("--host", default=None, help="address to listen on (overrides the config)")
    p.add_argument("--port", type=int, default=None, help="TCP port (overrides the config)")
    p.add_argument(
        "--print-map", action="store_true", help="print the register map and error codes, exit"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:

    if args.print_map:
        print(format_register_map())
        return 0
    if args.port is not None and not 0 <= args.port <= 65535:
        raise ValueError(f"--port: expected 0..65535, got {args.port}")
    if args.host is not None:
        check_host(args.host, "--host")
    config_path = resolve_config(Path(args.config) if args.config else "plc")
    config = load_plc_config(config_path)
    try:
        check_runner(config.jobs.runner)
    except ValueError as exc:
        raise InputError(config_path, str(exc)) from None

    def listening(host: str, port: int) -> None:
        print(f"scanner serve: listening on {host}:{port}", flush=True)

    asyncio.run(serve(config, host=args.host, port=args.port, on_listening=listening))
    print("scanner serve: stopped", file=sys.stderr)
    return 0

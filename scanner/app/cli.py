"""The ``scanner`` command line (contract: ``shared/spec/interfaces.md``, section 3).

Every command exits 0 on success and non-zero with a one-line reason on standard error for bad
input, never with a bare traceback. Set ``SCANNER_DEBUG=1`` to see the traceback anyway.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence

from scanner import __version__
from scanner.app.commands import (
    batch,
    calibrate,
    check,
    demo,
    history,
    inspect,
    plan_scan,
    scan,
    serve,
    simulate,
    target,
)
from scanner.app.commands.judge import ACCEPTANCE, MEASURE
from scanner.core.memory import keep_freed_memory

#: The sub-commands in the order ``scanner --help`` lists them.
COMMANDS = (
    simulate,
    target,
    calibrate,
    check,
    scan,
    MEASURE,
    ACCEPTANCE,
    inspect,
    plan_scan,
    batch,
    demo,
    serve,
    history,
)

EXIT_BAD_INPUT = 2
EXIT_FAILED = 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scanner",
        description="Robot laser-line scanner: calibrate, check, scan, measure, serve a PLC.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for command in COMMANDS:
        command.register(sub)
    # -v also after the command (`scanner scan ... -v`); SUPPRESS keeps the one given before it.
    for command_parser in sub.choices.values():
        command_parser.add_argument(
            "-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
            help="log progress details",
        )  # fmt: skip
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    keep_freed_memory()  # (image-sized temporaries reuse their pages: scanner.core.memory)
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_BAD_INPUT
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("scanner: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError) as exc:
        # InputError, ConfigError and validation errors: one line naming the file and reason.
        if os.environ.get("SCANNER_DEBUG"):
            raise
        print(f"scanner {args.command}: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Exception as exc:  # a bug, not bad input: still one line, with a hint
        if os.environ.get("SCANNER_DEBUG"):
            raise
        print(
            f"scanner {args.command}: internal error: {type(exc).__name__}: {_one_line(exc)} "
            "(rerun with SCANNER_DEBUG=1 for the traceback)",
            file=sys.stderr,
        )
        return EXIT_FAILED


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


if __name__ == "__main__":
    sys.exit(main())

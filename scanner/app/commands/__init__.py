"""One module per ``scanner`` sub-command.

Each module defines ``register(subparsers)`` (adds its parser and sets ``func``) and the
function that runs it. Work happens in the packages; these modules only parse arguments,
report progress and print what a person needs.
"""

COMMAND_MODULES = (
    "simulate",
    "target",
    "calibrate",
    "check",
    "scan",
    "measure",
    "acceptance",
    "demo",
    "serve",
    "history",
)

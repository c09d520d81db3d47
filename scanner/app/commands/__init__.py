"""One module per ``scanner`` sub-command.

Each module defines ``register(subparsers)`` (adds its parser and sets ``func``) and the
function that runs it. Work happens in :mod:`scanner.app.stages`; these modules only parse
arguments, report progress and print what a person needs. The arguments several commands
share are declared here once.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from scanner.scanning.pipeline import ScanOptions
from scanner.stripe.profile import StripeOptions

__all__ = [
    "add_calibration",
    "add_cloud_judging",
    "add_out",
    "add_session",
    "positive_int",
    "scan_options",
]


def positive_int(text: str) -> int:
    """An argparse type: a whole number >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected >= 1, got {value}")
    return value


def add_session(p: argparse.ArgumentParser, kind: str) -> None:
    p.add_argument("session", type=Path, help=f"{kind} session folder (scan-session/1)")


def add_calibration(p: argparse.ArgumentParser, required: bool = True) -> None:
    help_text = (
        "calibration file (JSON)"
        if required
        else "calibration file the cloud was scanned with, when the cloud does not record it"
    )
    p.add_argument("--calibration", type=Path, required=required, help=help_text)


def add_out(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--out", type=Path, required=True, help=what)


def add_cloud_judging(
    p: argparse.ArgumentParser, option: str, what: str, strict: str, several: str = ""
) -> None:
    """The arguments of a command that judges a cloud against a config (plan or spec);
    ``several``: the command takes one or more clouds, and what several mean."""
    formats = "(.ply, .pcd, .e57, .xyz, .npy, ...)"
    if several:
        p.add_argument("cloud", type=Path, nargs="+", help=f"point clouds {formats}: {several}")
    else:
        p.add_argument("cloud", type=Path, help=f"point cloud {formats}")
    p.add_argument(
        option, required=True, help=f"{what}: a TOML file, or the name of one in configs/plans/"
    )
    add_out(p, "result to write (.json; .csv and .html beside)")
    add_calibration(p, required=False)
    p.add_argument("--strict", action="store_true", help=f"exit 1 when {strict}")


def scan_options(args: argparse.Namespace) -> ScanOptions:
    """The :class:`ScanOptions` that ``scanner scan``'s parsed arguments ask for.

    Parameters
    ----------
    args : argparse.Namespace
        Arguments parsed by the ``scan`` sub-command's parser.

    Returns
    -------
    ScanOptions
        Stripe mode, cloud filtering, ICP and extraction threads as given on the command line.
    """
    return ScanOptions(
        stripe=StripeOptions(
            end_lines=args.stretch_end_lines,
            flatten_background={"auto": None, "remove": True, "keep": False}[
                args.uneven_background
            ],
        ),
        mode=args.mode,
        voxel_mm=args.voxel_mm,
        outlier_neighbors=args.outliers,
        normals_radius_mm=args.normals_mm,
        icp=args.icp,
        workers=args.workers,
        keep_flagged=args.keep_flagged,
        max_incidence_deg=args.max_incidence_deg,
    )

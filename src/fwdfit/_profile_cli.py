"""The ``fwdfit profile`` command: TIFF stacks to a profile table and a radiograph plot.

A thin shell over :func:`fwdfit._radiograph.profile_from_stacks`: it parses options,
computes everything, then writes ``FILE.csv`` and ``FILE.png`` together (temporary
files renamed into place), so a failure leaves no output behind.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from ._errors import FwdfitError
from ._radiograph import (COMBINE_METHODS, RadiographProfile, Roi, plot_radiograph_png,
                          profile_from_stacks, write_profile_csv)
from ._tables import check_paths, temporary_path


def parse_roi(text: str, option: str) -> Roi:
    """Parse ``R0,R1,C0,C1`` (half-open pixel indices) given to ``option``."""
    parts = text.split(",")
    try:
        values = [int(part) for part in parts]
    except ValueError:
        values = []
    if len(values) != 4:
        raise FwdfitError(f"{option} must be R0,R1,C0,C1 (four integers), got {text!r}")
    return Roi(*values)


def add_profile_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register the ``profile`` subcommand; its handler is ``args.handler = run_profile``."""
    parser = subparsers.add_parser(
        "profile", help="turn TIFF stacks into a profile x_um,T,T_err",
        description="Normalise sample frames by open-beam and dark frames "
                    "(T = (I - D) / (O - D)), average the region of interest along its "
                    "rows and write FILE.csv (x_um,T,T_err) and FILE.png (the radiograph).")
    stack = "TIFF file (single- or multi-page), folder of TIFFs, or glob (quote it)"
    parser.add_argument("--sample", required=True, metavar="S", help=f"sample frames: {stack}")
    parser.add_argument("--open", required=True, metavar="O", help=f"open-beam frames: {stack}")
    parser.add_argument("--dark", required=True, metavar="D", help=f"dark frames: {stack}")
    parser.add_argument("--roi", required=True, metavar="R0,R1,C0,C1",
                        help="rows R0:R1 and columns C0:C1 (half-open pixel indices); "
                             "x is measured from column C0")
    parser.add_argument("--pixel-um", required=True, type=float, metavar="P",
                        help="pixel pitch, um")
    parser.add_argument("--out", required=True, type=Path, metavar="FILE.csv",
                        help="profile table; the plot goes to the same name with .png")
    parser.add_argument("--combine", choices=COMBINE_METHODS, default="median",
                        help="per-pixel combination of the frames (default: median; "
                             "mean rejects outliers)")
    parser.add_argument("--rotate", action="store_true",
                        help="rotate the ROI so its strongest edge runs along the columns")
    parser.add_argument("--dose-roi", metavar="R0,R1,C0,C1",
                        help="sample-free region: divide T by its mean there")
    parser.set_defaults(handler=run_profile)
    return parser


def _write_outputs(profile: RadiographProfile, csv_path: Path, png_path: Path) -> None:
    """Write the table and the plot to temporary files, then rename both into place."""
    csv_path.parent.mkdir(parents=True, exist_ok=True)
    with temporary_path(csv_path) as csv_temp, temporary_path(png_path) as png_temp:
        write_profile_csv(csv_temp, profile.x_um, profile.T, profile.T_err)
        plot_radiograph_png(png_temp, profile.image, profile.roi)
        os.replace(csv_temp, csv_path)
        os.replace(png_temp, png_path)


def run_profile(args: argparse.Namespace) -> None:
    """Handle ``fwdfit profile``: write ``args.out`` (.csv) and the same stem with .png."""
    roi = parse_roi(args.roi, "--roi")
    dose_roi = None if args.dose_roi is None else parse_roi(args.dose_roi, "--dose-roi")
    if args.out.suffix.lower() != ".csv":
        raise FwdfitError(f"--out must name a .csv file, got {args.out}")
    check_paths(out_file=args.out)
    check_paths(out_file=args.out.with_suffix(".png"))
    profile = profile_from_stacks(args.sample, args.open, args.dark, roi, args.pixel_um,
                                  combine=args.combine, rotate=args.rotate, dose_roi=dose_roi)
    _write_outputs(profile, args.out, args.out.with_suffix(".png"))

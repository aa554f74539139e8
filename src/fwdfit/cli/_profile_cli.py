"""The ``fwdfit profile`` command: TIFF stacks to a profile table and a radiograph plot,
or (``--tof``) time-of-flight stacks to one profile per wavelength bin.

A thin shell over :func:`fwdfit._radiograph.profile_from_stacks` and
:func:`fwdfit._tof.tof_profiles`: it parses options, computes everything, then writes
``FILE.csv`` and ``FILE.png`` together (temporary files renamed into place), or the
folder of bins (staged, then moved into place), so a failure leaves no output behind;
then one line on stdout says what it wrote.
"""

from __future__ import annotations

import argparse
import math
import os
from contextlib import ExitStack
from pathlib import Path

from .._errors import FwdfitError
from ..images._radiograph import (COMBINE_METHODS, RadiographProfile, Roi, plot_radiograph_png,
                          profile_from_stacks, write_profile_csv)
from ..io._tables import check_paths, staged_folder, temporary_path, write_columns

# Options that only --tof reads, with their "not given" values.
TOF_ONLY = {"flight_path_m": None, "tof_offset_us": 0.0, "rebin": 1, "dataset": None,
            "tof_dataset": None, "errors": "rows", "distance_mm": None}


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
                    "rows and write FILE.csv (x_um,T,T_err) and FILE.png (the radiograph "
                    "and the profile with its errors). "
                    "With --tof: time-of-flight stacks (a folder of per-bin FITS files with "
                    "its *_Spectra.txt, or an HDF5/NeXus histogram), one profile per "
                    "wavelength bin written to the folder --out with wavelengths.csv and a "
                    "scene skeleton scene.toml.")
    stack = ("TIFF file (single- or multi-page), folder of TIFFs, or glob (quote it); with "
             "--tof a folder of FITS bins or an HDF5/NeXus file")
    parser.add_argument("--sample", required=True, metavar="S", help=f"sample frames: {stack}")
    parser.add_argument("--open", required=True, metavar="O", help=f"open-beam frames: {stack}")
    parser.add_argument("--dark", metavar="D",
                        help=f"dark frames: {stack} (required without --tof)")
    parser.add_argument("--roi", required=True, metavar="R0,R1,C0,C1",
                        help="rows R0:R1 and columns C0:C1 (half-open pixel indices); "
                             "x is measured from column C0")
    parser.add_argument("--pixel-um", required=True, type=float, metavar="P",
                        help="pixel pitch, um")
    parser.add_argument("--out", required=True, type=Path, metavar="FILE.csv",
                        help="profile table; the plot goes to the same name with .png "
                             "(with --tof: an output folder)")
    parser.add_argument("--combine", choices=COMBINE_METHODS, default=None,
                        help="per-pixel combination of the frames (default: median; "
                             "mean rejects outliers); not with --tof")
    parser.add_argument("--rotate", action="store_true",
                        help="rotate the ROI so its strongest edge runs along the columns")
    parser.add_argument("--dose-roi", metavar="R0,R1,C0,C1",
                        help="sample-free region: divide T by its mean there")
    tof = parser.add_argument_group("time of flight (--tof)")
    tof.add_argument("--tof", action="store_true",
                     help="the stacks hold one image per time-of-flight bin")
    tof.add_argument("--flight-path-m", type=float, metavar="L",
                     help="source to detector, m (required with --tof): "
                          "lambda[A] = 3956.034 t[s] / L[m]")
    tof.add_argument("--tof-offset-us", type=float, default=0.0, metavar="DT",
                     help="added to every recorded time of flight, us (default 0)")
    tof.add_argument("--rebin", type=int, default=1, metavar="N",
                     help="sum N adjacent bins (the last group takes the rest; default 1)")
    tof.add_argument("--errors", choices=("rows", "counts"), default="rows",
                     help="T_err from the spread over the ROI rows (default) or from Poisson "
                          "counting statistics (integer counts)")
    tof.add_argument("--dataset", metavar="PATH",
                     help="HDF5: the (bins, rows, columns) histogram (default: the NeXus "
                          "default signal)")
    tof.add_argument("--tof-dataset", metavar="PATH",
                     help="HDF5: bin times of flight, centres or edges, with a units attribute "
                          "(default: the NeXus axis time_of_flight or tof beside the data)")
    tof.add_argument("--distance-mm", type=float, metavar="D",
                     help="sample centre to detector, mm, written into the scene skeleton")
    parser.set_defaults(handler=run_profile)
    return parser


def _write_outputs(profile: RadiographProfile, csv_path: Path, png_path: Path) -> None:
    """Write the table and the plot to temporary files, then rename both into place."""
    csv_path.parent.mkdir(parents=True, exist_ok=True)
    with temporary_path(csv_path) as csv_temp, temporary_path(png_path) as png_temp:
        write_profile_csv(csv_temp, profile.x_um, profile.T, profile.T_err)
        plot_radiograph_png(png_temp, profile)
        os.replace(csv_temp, csv_path)
        os.replace(png_temp, png_path)


def _option(name: str) -> str:
    return "--" + name.replace("_", "-")


def run_profile(args: argparse.Namespace) -> None:
    """Handle ``fwdfit profile``: write ``args.out`` (.csv) and the same stem with .png;
    with ``--tof`` the folder ``args.out`` (:func:`run_tof_profile`)."""
    roi = parse_roi(args.roi, "--roi")
    dose_roi = None if args.dose_roi is None else parse_roi(args.dose_roi, "--dose-roi")
    if args.tof:
        run_tof_profile(args, roi, dose_roi)
        return
    given = [_option(name) for name, unset in TOF_ONLY.items() if getattr(args, name) != unset]
    if given:
        raise FwdfitError(f"{given[0]} applies to --tof only")
    if args.dark is None:
        raise FwdfitError("the following arguments are required: --dark")
    if args.out.suffix.lower() != ".csv":
        raise FwdfitError(f"--out must name a .csv file, got {args.out}")
    check_paths(out_file=args.out)
    check_paths(out_file=args.out.with_suffix(".png"))
    profile = profile_from_stacks(args.sample, args.open, args.dark, roi, args.pixel_um,
                                  combine=args.combine or "median", rotate=args.rotate,
                                  dose_roi=dose_roi)
    _write_outputs(profile, args.out, args.out.with_suffix(".png"))
    print(f"wrote {args.out} ({len(profile.x_um)} pixels), {args.out.with_suffix('.png')}")


def run_tof_profile(args: argparse.Namespace, roi, dose_roi) -> None:
    """Write ``binNNN.csv`` per wavelength bin, ``wavelengths.csv`` and ``scene.toml``
    into the folder ``args.out`` (all computed first, then moved in together)."""
    from ..tof._tof import tof_profiles
    from ..io._tof_read import open_tof_stack
    from ..tof._tof_scene import bin_names, skeleton_toml

    if args.flight_path_m is None:
        raise FwdfitError("--tof needs --flight-path-m (source to detector, m)")
    if args.combine is not None:
        raise FwdfitError("--combine does not apply with --tof (one image per bin)")
    if args.distance_mm is not None and not (math.isfinite(args.distance_mm)
                                             and args.distance_mm > 0):
        raise FwdfitError(f"--distance-mm must be positive, got {args.distance_mm}")
    check_paths(out_dir=args.out)
    if args.out.exists() and any(args.out.iterdir()):
        raise FwdfitError(f"--out {args.out}: folder exists and is not empty")
    with ExitStack() as stacks:
        def open_stack(spec):
            return stacks.enter_context(open_tof_stack(spec, args.dataset, args.tof_dataset))

        sample, open_beam = open_stack(args.sample), open_stack(args.open)
        dark = None if args.dark is None else open_stack(args.dark)
        profiles = tof_profiles(sample, open_beam, dark, roi, args.pixel_um, args.flight_path_m,
                                tof_offset_us=args.tof_offset_us, rebin=args.rebin,
                                rotate=args.rotate, dose_roi=dose_roi, errors=args.errors)
    names = bin_names(len(profiles.T))
    header = (f"Scene skeleton written by fwdfit profile --tof: {len(names)} wavelength bins of "
              f"{args.sample}\nflight path {args.flight_path_m:g} m, time offset "
              f"{args.tof_offset_us:g} us, rebin {args.rebin}, ROI {args.roi}")
    if profiles.angle_deg:
        header += f", rotated by {profiles.angle_deg:.4f} deg"
    scene = skeleton_toml(profiles.wavelength_edges_A, profiles.x_um, args.pixel_um, args.out,
                          distance_mm=args.distance_mm, header=header)
    edges_s, edges_A = profiles.tof_edges_s, profiles.wavelength_edges_A
    with staged_folder(args.out) as staging:
        for name, T, T_err in zip(names, profiles.T, profiles.T_err):
            write_profile_csv(staging / f"{name}.csv", profiles.x_um, T, T_err)
        write_columns(staging / "wavelengths.csv", {
            "bin": range(len(names)), "tof_min_us": edges_s[:-1] * 1e6,
            "tof_max_us": edges_s[1:] * 1e6, "lambda_min_A": edges_A[:-1],
            "lambda_max_A": edges_A[1:]})
        (staging / "scene.toml").write_text(scene, encoding="utf-8")
    print(f"wrote {len(names)} wavelength bins ({edges_A[0]:.4g} to {edges_A[-1]:.4g} A) "
          f"to {args.out}")

"""Fit refraction at sample edges and interfaces out of neutron radiographs.

The ``fwdfit`` command line, a thin shell over the library (no physics here): every
command exits 0 on success and 1 with a one-line ``fwdfit: error: ...`` on bad input
(options included), writing nothing; Ctrl-C prints ``fwdfit: interrupted`` and exits
130, also writing nothing. Outputs and inputs are checked before any work; an output
folder never holds an input. Progress goes to stderr, results to stdout. Only the
standard library is imported before the Ctrl-C handler is in place.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from pathlib import Path

from .._errors import FwdfitError, ModelWarning
from .._interrupt import EXIT_INTERRUPTED, install_interrupt_handler
from .._progress import Progress
from .._version import __version__

_CACHE = ("Compiled models are kept in FWDFIT_CACHE_DIR (default $XDG_CACHE_HOME/fwdfit, else "
          "~/.cache/fwdfit; 'off' disables).")
EXIT_NOT_CONVERGED = 2  # fit: results written, the solver did not converge
EXIT_REJECTED = 3  # fit: results written, converged, but the data reject the model


class _Parser(argparse.ArgumentParser):
    """argparse with fwdfit's convention for bad options: one line, exit status 1."""

    def error(self, message):
        raise FwdfitError(message)


def _in_domain(key: str):
    """An argparse ``type``: a number inside the validity domain of ``key`` (the same
    check as the scene key of that name); argparse names the option in its message."""
    def parse(text: str) -> float:
        from ..scene._limits import domain_problem

        value = float(text)  # a ValueError: argparse says "invalid <key> value: ..."
        problem = domain_problem(key, value)
        if problem:
            raise argparse.ArgumentTypeError(problem)
        return value

    parse.__name__ = key
    return parse


def _quiet_xla() -> None:
    """Keep XLA's own C++ log (its "Very slow compile?" alarm, ...) off the terminal.

    jax reads TF_CPP_MIN_LOG_LEVEL only when it is imported (before this module), so the
    level is set through jax's config instead (an option of recent jax versions).
    """
    import jax

    try:
        jax.config.update("jax_logging_level", "CRITICAL")
    except AttributeError:  # an older jax: its log stays on
        pass


def _use_cache(args) -> None:
    """The persistent cache of compiled programs, unless ``--no-cache``."""
    if not args.no_cache:
        from ..inference._cache import enable_compilation_cache

        enable_compilation_cache()


def _enable_float64() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)


def _scene_of(args):
    """The scene of a command, its output folder checked: writable, and holding no input."""
    from ..scene._scene import load_scene  # looked up when run
    from ..io._tables import check_paths, refuse_inputs_in

    check_paths([args.scene], out_dir=args.out)
    scene = load_scene(args.scene)
    refuse_inputs_in(args.out, scene.input_files())
    return scene


def _run_simulate(args) -> None:
    from .. import simulate  # looked up when run: a test may replace it
    from ..inference._simulate import write_simulation

    _enable_float64()
    scene = _scene_of(args)
    _use_cache(args)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default", ModelWarning)
        profiles = simulate(scene, args.accuracy, progress=args.say)
    for warning in caught:
        _print_warning(warning.message, warning.category, warning.filename, warning.lineno)
    write_simulation(profiles, Path(args.out),
                     [str(w.message) for w in caught if issubclass(w.category, ModelWarning)])
    print(f"wrote {len(profiles)} profile(s) to {args.out}")


def _run_paganin(args) -> None:
    from ..io._tables import staged_folder, write_columns
    from ..paganin import paganin_layer, paganin_profiles

    scene = _scene_of(args)
    profiles = paganin_profiles(scene, material=args.material, b_factor=args.b_factor,
                                mode=args.mode)
    layer = paganin_layer(scene, args.material).name
    out = Path(args.out)
    with staged_folder(out) as staging:
        for p in profiles:
            write_columns(staging / f"{p.name}.csv",
                          {"x_um": p.x_um, "T": p.T, "T_filtered": p.T_filtered})
    chosen = "as named" if args.material else "the thickest layer; --material to choose"
    print(f"filter constants of layer {layer} ({chosen}), b_factor {args.b_factor:g}, mode {args.mode}")
    for p in profiles:
        print(f"{p.name}: tau = {p.tau_um2:.6g} um^2 (kernel length {p.tau_um2 ** 0.5:.3g} um) "
              f"-> {out / (p.name + '.csv')}")


def _run_fit(args) -> int:
    from .. import Fitter, write_fit

    _enable_float64()
    scene = _scene_of(args)
    if args.starts < 1:
        raise FwdfitError(f"--starts must be >= 1, got {args.starts}")
    if args.sample is not None:
        _check_sampling(args)
    _use_cache(args)
    with warnings.catch_warnings():
        _notes_with_the_table()
        fitter = Fitter(scene, accuracy=args.accuracy, n_starts=args.starts, max_steps=args.max_steps,
                        progress=args.say)
        result = fitter(seed=args.seed)
    posterior = None if args.sample is None else _sample_posterior(args, fitter, result)
    write_fit(result, Path(args.out))
    print(result.table())
    print(f"compile {result.compile_time_s:.1f} s, fit {result.wall_time_s:.1f} s; wrote {args.out}")
    if posterior is not None:
        from ..outputs._sample_output import write_posterior

        write_posterior(posterior, Path(args.out))
        print(posterior.table())
    for note in result.warnings:
        if note != result.quality.summary():  # said once, below
            print(f"warning: {note}", file=sys.stderr)
    if not result.converged:
        return EXIT_NOT_CONVERGED
    if not result.quality.passed:
        print(f"fwdfit: poor fit: {result.quality.summary()}", file=sys.stderr)
        return EXIT_REJECTED
    return 0


def _run_fit_image(args) -> int:
    from ..images._image_fit import FLAG_POOR_FIT, fit_image
    from ..images._image_output import write_image_fit

    _enable_float64()
    scene = _scene_of(args)
    _use_cache(args)
    with warnings.catch_warnings():
        _notes_with_the_table()
        result = fit_image(scene, accuracy=args.accuracy, progress=args.say)
    write_image_fit(result, Path(args.out))
    shared = result.shared
    print(shared.table())
    print(f"{result.summary()}; compile {result.compile_time_s:.1f} s, fit {result.wall_time_s:.1f} s; "
          f"wrote {args.out}")
    for note in shared.warnings:
        print(f"warning: shared fit of the averaged rows: {note}", file=sys.stderr)
    if result.n_masked:
        print(f"warning: {result.n_masked} masked (non-finite) pixels left out of the fit", file=sys.stderr)
    flagged = int((result.flags != 0).sum())
    if flagged:
        print(f"warning: {flagged} of {len(result.flags)} rows flagged (see the flag column of rows.csv)",
              file=sys.stderr)
    if not shared.converged:
        return EXIT_NOT_CONVERGED
    if not result.accepted:
        poor = int((result.flags & FLAG_POOR_FIT != 0).sum())
        print(f"fwdfit: poor fit: {poor} of {int(result.fitted.sum())} fitted rows fit poorly "
              "(flag 4 in rows.csv)", file=sys.stderr)
        return EXIT_REJECTED
    return 0


def _run_fit_images(args) -> int:
    from ..images._image_fit import _image_profile, _names
    from ..images._image_series import STATUS_OK, check_images, find_images, fit_series
    from ..io._tables import refuse_inputs_in

    scene = _scene_of(args)
    if args.workers is not None and args.scheduler is not None:
        raise FwdfitError("--workers is for a local cluster; with --scheduler the cluster's workers fit")
    workers = args.workers if args.workers is not None else (1 if args.scheduler else os.cpu_count() or 1)
    if workers < 1:
        raise FwdfitError(f"--workers must be >= 1, got {workers}")
    profile = _image_profile(scene)
    _names(scene, profile)  # [fit] fits an image: refused here, not once per image
    images = find_images(args.images)
    refuse_inputs_in(args.out, images)
    check_images(images, profile.image.shape)
    say = args.say
    if profile.image_err is not None:
        say("note: image_err of the template is not used; each image's noise is estimated from the image")
    lines = fit_series(args.scene, images, args.out, scheduler=args.scheduler, workers=workers,
                       accuracy=args.accuracy, cache=not args.no_cache, say=say)
    bad = [line for line in lines if line["status"] != STATUS_OK]
    print(f"{len(lines) - len(bad)} of {len(lines)} images fitted well; wrote {Path(args.out) / 'summary.csv'}")
    if bad:
        names = ", ".join(f"{line['image']} ({line['status']})" for line in bad[:5])
        print(f"fwdfit: {len(bad)} image(s) not fitted well: {names}{', ...' if len(bad) > 5 else ''}",
              file=sys.stderr)
        return EXIT_REJECTED
    return 0


def _check_sampling(args) -> None:
    """Refuse bad sampling options, and a missing blackjax, before the fit."""
    from ..inference._sample import blackjax_module

    for option, value, least in (("--sample", args.sample, 1), ("--chains", args.chains, 1),
                                 ("--warmup", args.warmup, 10)):
        if value is not None and value < least:
            raise FwdfitError(f"{option} must be >= {least}, got {value}")
    blackjax_module()


def _sample_posterior(args, fitter, result):
    from ..inference._sample import sample

    args.say(f"sampling: {args.chains} chains, {args.sample} draws each after warm-up")
    return sample(fitter.scene, args.sample, chains=args.chains, warmup=args.warmup, seed=args.seed,
                  fitter=fitter, result=result)


def _run_design(args) -> None:
    from ..inference._design import design
    from ..outputs._design_output import design_dict, write_design

    _enable_float64()
    scene = _scene_of(args)
    _use_cache(args)
    plan = design(scene, target=args.target or None, exposure=args.exposure, accuracy=args.accuracy,
                  progress=args.say)
    write_design(plan, Path(args.out))
    summary = design_dict(plan)
    for name, errors in ((n, p["errors"]) for n, p in summary["plans"].items()):
        text = ", ".join(f"{t} ± {errors[t]:.3g}" if errors[t] is not None else f"{t} undetermined"
                         for t in summary["targets"])
        print(f"{name:>8}: {text}")
    used = ", ".join(f"{m['spectrum']} at {m['distance_mm']:g} mm: {m['exposure']:.3g}"
                     for m in summary["plans"]["optimal"]["measurements"])
    print(f"optimal plan (exposure per measurement): {used}")
    print(f"wrote design.json, design.csv, design.png to {args.out}")


def build_parser() -> argparse.ArgumentParser:
    """The command line's argument parser (every command and option)."""
    from ..paganin._paganin_scene import MODES as PAGANIN_MODES
    from ._profile_cli import add_profile_parser

    parser = _Parser(prog="fwdfit", description=__doc__.splitlines()[0],
                     epilog="Exit status: 0 success, 1 bad input (nothing written), 2 a fit did not "
                            "converge, 3 the data reject a fit, 130 interrupted. 'fwdfit COMMAND --help' "
                            "for a command's options.")
    parser.add_argument("--version", action="version", version=f"fwdfit {__version__}")
    commands = parser.add_subparsers(dest="command", required=True)
    simulate = commands.add_parser("simulate", help="predict T and T_att for every profile of a scene",
                                   description=f"Writes DIR/<profile>.csv with columns x_um,T,T_att. {_CACHE}")
    _add_scene_options(simulate, "scene file (TOML)", "output folder for <profile>.csv")
    _add_run_options(simulate)
    simulate.set_defaults(handler=_run_simulate)
    paganin = commands.add_parser(
        "paganin", help="apply the single-material Paganin-type filter to every measured profile",
        description="T_filtered = F^-1[F[T] / (1 + tau k^2)] with tau from one layer's SLD and "
                    "mu, the profile's wavelength, distance and beam divergence D/L; writes "
                    "DIR/<profile>.csv with columns x_um,T,T_filtered.")
    _add_scene_options(paganin, "scene file (TOML) whose profiles are measured (file =)",
                       "output folder for <profile>.csv", accuracy=False)
    paganin.add_argument("--quiet", action="store_true", help="no progress output")
    paganin.add_argument("--b-factor", type=_in_domain("b_factor"), default=1.0, metavar="F",
                         help="multiplies the layer's SLD in tau (default 1; the paper needed 40)")
    paganin.add_argument("--material", metavar="LAYER", default=None,
                         help="layer whose constants the filter uses (default: the thickest)")
    paganin.add_argument("--mode", choices=PAGANIN_MODES,
                         default="mean_wavelength",
                         help="tau at the spectrum's mean wavelength (default) or averaged "
                              "over the spectrum")
    paganin.set_defaults(handler=_run_paganin)
    fit = _fit_command(commands, "fit", "scene file (TOML) with measured profiles and a [fit] table", _run_fit,
                       help="fit the [fit] parameters to every measured profile at once",
                       description="Exit status 0: a good fit; 1: bad input; 2: results written but the "
                                   "solver did not converge; 3: results written, but the data reject the "
                                   f"fit (one line says where); 130: interrupted. {_CACHE}")
    fit.add_argument("--starts", type=int, default=1,
                     help="N > 1 adds N - 1 random starts inside the bounds to the global scan's best "
                          "points (default 1: the scan alone)")
    fit.add_argument("--seed", type=int, default=0, help="seed for the random starting points")
    fit.add_argument("--max-steps", type=int, default=200, help="solver steps (default 200)")
    fit.add_argument("--sample", type=int, default=None, metavar="N",
                     help="after the fit, N posterior draws per chain with NUTS (needs fwdfit[sample]): "
                          "DIR/chains.csv, posterior.json, corner.png")
    fit.add_argument("--chains", type=int, default=4, metavar="C", help="NUTS chains (default 4)")
    fit.add_argument("--warmup", type=int, default=None, metavar="W",
                     help="NUTS warm-up steps per chain (default max(300, N/2))")
    _fit_command(commands, "fit-image", "scene file (TOML) whose one profile is an image, with a [fit] table",
                 _run_fit_image,
                 help="fit a whole normalised image row by row (shared material, a centre per row)",
                 description="The scene's one profile names image = T.tif. Writes T_att.tif, T_corrected.tif, "
                             "residual.tif, rows.csv, result.json and overview.png. Exit status as fwdfit fit "
                             "(2: the shared fit did not converge; 3: more than 5 % of the fitted rows fit "
                             "poorly); flagged rows are named in rows.csv.")
    series = _fit_command(
        commands, "fit-images", "scene file (TOML) whose one profile is an image: the template", _run_fit_images,
        help="fit many images (a tomography or time series) with one scene as template",
        description="Each image is fitted as fit-image fits the scene's image and written to DIR/<image "
                    "name>/; images whose folder is complete are skipped (an interrupted run resumes). "
                    "DIR/summary.csv has a line per image. Exit status 0: every image fitted well; "
                    "3: an image's fit failed, did not converge or was rejected; 1: bad input.")
    series.add_argument("images", nargs="+", metavar="IMAGES",
                        help="TIFF files, folders of them, or globs ('proj_*.tif'), each with the template's "
                             "rows and columns")
    series.add_argument("--scheduler", metavar="ADDRESS", default=None,
                        help="a Dask scheduler to fit on (tcp://host:8786), else a local cluster")
    series.add_argument("--workers", type=int, default=None, metavar="N",
                        help="local Dask worker processes (default: the machine's cores); 1: serially in "
                             "this process, no Dask needed")
    plan = commands.add_parser(
        "design", help="plan measurements: the distances and spectra that best determine chosen parameters",
        description="From the model's derivatives at the scene's values, the Fisher information of each "
                    "candidate measurement ([design] distances_mm x spectra, and the scene's own); the "
                    "exposure split that minimises the targets' predicted errors within the total "
                    "exposure. Writes design.json, design.csv and design.png. " + _CACHE)
    _add_scene_options(plan, "scene file (TOML) with a [fit] table (its values: the expected sample)",
                       "output folder for design.json, design.csv, design.png")
    plan.add_argument("--target", action="append", metavar="NAME",
                      help="a parameter to plan for (repeatable; default: [design] target, else every "
                           "shared free parameter)")
    plan.add_argument("--exposure", type=float, default=None, metavar="E",
                      help="total exposure in units of one profile's (default: [design] exposure, else "
                           "the number of profiles)")
    _add_run_options(plan)
    plan.set_defaults(handler=_run_design)
    add_profile_parser(commands)
    return parser


def _add_scene_options(command: argparse.ArgumentParser, scene_help: str, out_help: str = "output folder",
                       accuracy: bool = True) -> None:
    """The scene, --out and (if ``accuracy``) --accuracy."""
    command.add_argument("scene", help=scene_help)
    command.add_argument("--out", required=True, metavar="DIR", help=out_help)
    if accuracy:
        command.add_argument("--accuracy", type=_in_domain("accuracy"), default=None,
                             help="target RMS error in T, 1e-5 to 0.1 (default: the scene's, else 1e-3)")


def _fit_command(commands, name: str, scene_help: str, handler, **texts) -> argparse.ArgumentParser:
    """A fit command: the scene, --out and the options every fit command takes."""
    command = commands.add_parser(name, **texts)
    _add_scene_options(command, scene_help)
    _add_run_options(command)
    command.set_defaults(handler=handler)
    return command


def _add_run_options(command: argparse.ArgumentParser) -> None:
    """--quiet and --no-cache, for the commands that compile the model."""
    command.add_argument("--quiet", action="store_true", help="no progress output (stderr)")
    command.add_argument("--no-cache", action="store_true",
                         help="compile without the cache folder of compiled programs")


def _notes_with_the_table() -> None:
    """Inside ``warnings.catch_warnings``: a fit's notes wait for its table; a model less exact
    than asked (``ModelWarning``) is said at once."""
    warnings.simplefilter("ignore")
    warnings.simplefilter("default", ModelWarning)


def _print_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings as one ``warning:`` line on stderr, without the source line."""
    print(f"warning: {message}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    """Run one command; returns its exit status: 0, 1 bad input, 130 interrupted (fit: more)."""
    install_interrupt_handler()

    try:
        args = build_parser().parse_args(argv)
        args.say = Progress(not getattr(args, "quiet", False))
        _quiet_xla()
        with warnings.catch_warnings():  # restores the printer
            warnings.showwarning = _print_warning
            status = args.handler(args)
    except (FwdfitError, OSError) as error:
        message = str(error).splitlines()[0] if str(error) else type(error).__name__
        print(f"fwdfit: error: {message}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # raised by a library caller's code, not by the handler
        print("fwdfit: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    return status or 0


if __name__ == "__main__":
    sys.exit(main())

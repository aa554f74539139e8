"""The ``fwdfit`` command line: a thin shell over the library (no physics here).

Every command exits 0 on success and 1 with a one-line ``fwdfit: error: ...`` on
bad input, writing nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ._errors import FwdfitError
from ._profile_cli import add_profile_parser


def _enable_float64() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)


def _run_simulate(args) -> None:
    from ._scene import load_scene
    from ._simulate import simulate, write_simulation

    _enable_float64()
    scene = load_scene(args.scene)
    profiles = simulate(scene, args.accuracy)
    write_simulation(profiles, Path(args.out))
    print(f"wrote {len(profiles)} profile(s) to {args.out}")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fwdfit", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    simulate = commands.add_parser("simulate", help="predict T and T_att for every profile of a scene")
    simulate.add_argument("scene", help="scene file (TOML)")
    simulate.add_argument("--out", required=True, help="output folder for <profile>.csv")
    simulate.add_argument("--accuracy", type=float, default=None,
                          help="target RMS error in T (default: the scene's, else 1e-3)")
    simulate.set_defaults(handler=_run_simulate)
    add_profile_parser(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        args.handler(args)
    except (FwdfitError, OSError) as error:
        message = str(error).splitlines()[0] if str(error) else type(error).__name__
        print(f"fwdfit: error: {message}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

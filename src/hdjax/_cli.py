"""Shared command-line plumbing: target resolution, output folder, float64, clean errors."""

import argparse
import os
import pathlib
import sys


def main_wrapper(prog: str, description: str, run) -> int:
    """Parse `TARGET [--out DIR]`, switch on float64, call `run(dataset, config, out)`, and turn
    bad input into a one-paragraph message with exit status 2."""
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")  # silence XLA's C++ log chatter
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument("target", help="config YAML (naming a dataset folder and options) or a dataset folder")
    parser.add_argument("--out", default=None, help="output folder (default: results/<target name>)")
    args = parser.parse_args()

    import jax

    jax.config.update("jax_enable_x64", True)
    from ._data import DatasetError, resolve_target

    try:
        dataset, config = resolve_target(args.target)
    except DatasetError as e:
        print(f"{prog}: bad input: {e}", file=sys.stderr)
        return 2
    target = pathlib.Path(args.target)
    out = pathlib.Path(args.out) if args.out else pathlib.Path("results") / (target.stem if target.suffix else target.name)
    try:
        run(dataset, config, out)
    except (DatasetError, ValueError) as e:
        print(f"{prog}: cannot run on {args.target}: {e}", file=sys.stderr)
        return 2
    return 0

"""`python -m hdjax.fit TARGET [--out DIR]`: the paper's identification, then the joint
trajectory-error fit; writes fit.json, report.md and figures (SPEC §3)."""

import sys

from ._cli import main_wrapper


def _run(dataset, config, out):
    from ._friction_cli import is_friction_only, run_fit as run_friction_fit

    if is_friction_only(dataset):
        return run_friction_fit(dataset, config, out)
    from ._identify import run_fit

    run_fit(dataset, config, out)


if __name__ == "__main__":
    sys.exit(main_wrapper("hdjax.fit", __doc__, _run))

"""`python -m hdjax.fit TARGET [--out DIR] [--quiet]` (the same as `hdjax fit`): the paper's
identification, then the joint trajectory-error fit; writes fit.json, report.md, report.html,
run.log and figures (SPEC §3). Friction-only datasets get the eq. 9 fit.

`run_fit(dataset, config, out)` is the workflow behind it (dynamic data), for scripts."""

import sys

from ._workflows.cli import command_main
from ._workflows.fit import run_fit as run_fit

main = command_main("fit")

if __name__ == "__main__":
    sys.exit(main())

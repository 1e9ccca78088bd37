"""`python -m hdjax.sensitivity TARGET [--out DIR] [--fit FIT_JSON] [--quiet]` (the same as
`hdjax sensitivity`): normalised sensitivities by forward-mode AD, Fisher-information standard
errors, correlations and weakest parameter directions, the paper's section V study (Coulomb = 0,
viscous = 0, K1/10, Tst = 0) and experiment-design advice; writes sensitivity.json, report.md,
report.html, run.log and figures (SPEC §3; default folder results/<name>-sensitivity).

Parameter values: `--fit FIT_JSON` (or the config key `sensitivity: {fit_json: PATH}`), else
`results/<name>/fit.json` beside the default output folder `results/<name>-sensitivity` when it
belongs to the same dataset, else the paper's identification (section III regressions).
"""

import sys

from ._workflows.cli import command_main

main = command_main("sensitivity")

if __name__ == "__main__":
    sys.exit(main())

"""`python -m hdjax.tune TARGET [--out DIR] [--fit FIT_JSON] [--quiet]` (the same as `hdjax
tune`): a torque controller (PI(D) on measured torque plus friction feed-forward) tuned by gradient
through the identified plant, robust over the per-experiment estimates, validated on the bench
against a relay/Ziegler–Nichols PI; writes tune.json, report.md, report.html, run.log and figures
(SPEC §3; default folder results/<name>-tune). Uses `--fit`, config `tune.fit`, DIR/fit.json or
results/<dataset>/fit.json when present, else runs the paper's identification.

`run_tune(dataset, config, out)` is the workflow behind it, and `bench_tracking_cost` the bench
validation cost of given gains, for scripts."""

import sys

from ._workflows.cli import command_main
from ._workflows.tune import bench_tracking_cost as bench_tracking_cost, run_tune as run_tune

main = command_main("tune")

if __name__ == "__main__":
    sys.exit(main())

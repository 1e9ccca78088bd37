"""`python -m hdjax.tune TARGET [--out DIR]`: a torque controller (PI(D) on measured torque plus
friction feed-forward) tuned by gradient through the identified plant, robust over the
per-experiment estimates, validated on the bench against a relay/Ziegler–Nichols PI; writes
tune.json, report.md and figures (SPEC §3). Uses DIR/fit.json or results/<dataset>/fit.json when
present, else runs the paper's identification."""

import sys

from ._cli import main_wrapper


def _run(dataset, config, out):
    from ._tune import run_tune

    run_tune(dataset, config, out)


if __name__ == "__main__":
    sys.exit(main_wrapper("hdjax.tune", __doc__, _run))

"""`python -m hdjax.diagnose TARGET [--out DIR]`: what the fitted paper model gets wrong, which
SPEC §4 effect explains it, and the held-out gain of the extended model; writes diagnosis.json,
extended_model.json, report.md and figures."""

import sys

from ._cli import main_wrapper


def _run(dataset, config, out):
    from ._friction_cli import is_friction_only, run_diagnose as run_friction_diagnose

    out = out.with_name(out.name + "-diagnosis") if out.parent.name == "results" else out
    if is_friction_only(dataset):
        return run_friction_diagnose(dataset, config, out)
    from ._diagnose_report import run_diagnose

    run_diagnose(dataset, config, out)


if __name__ == "__main__":
    sys.exit(main_wrapper("hdjax.diagnose", __doc__, _run))

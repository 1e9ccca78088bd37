"""`python -m hdjax.diagnose TARGET [--out DIR] [--quiet]` (the same as `hdjax diagnose`): what
the fitted paper model gets wrong, which SPEC §4 effect explains it, and the held-out gain of the
extended model; writes diagnosis.json, extended_model.json, report.md, report.html, run.log and
figures (default folder results/<name>-diagnosis)."""

import sys

from ._workflows.cli import command_main

main = command_main("diagnose")

if __name__ == "__main__":
    sys.exit(main())

"""`python -m hdjax.sensitivity TARGET [--out DIR] [--fit FIT_JSON]`: normalised sensitivities by
forward-mode AD, Fisher-information standard errors, correlations and weakest parameter directions,
the paper's section V study (Coulomb = 0, viscous = 0, K1/10, Tst = 0) and experiment-design advice;
writes sensitivity.json, report.md and figures (SPEC §3).

Parameter values: `--fit FIT_JSON` (or the config key `sensitivity: {fit_json: PATH}`), else
`results/<name>/fit.json` beside the default output folder `results/<name>-sensitivity` when it
belongs to the same dataset, else the paper's identification (section III regressions).
"""

import pathlib
import sys

from ._cli import main_wrapper


def _run_with(fit_json):
    def _run(dataset, config, out):
        from ._sensitivity import run_sensitivity

        if fit_json is not None:
            config = dict(config or {})
            config["sensitivity"] = dict(config.get("sensitivity") or {}, fit_json=fit_json)
        run_sensitivity(dataset, config, out)

    return _run


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    fit_json = None
    rest = []
    i = 0
    while i < len(argv):
        a = argv[i]
        if a == "--fit" and i + 1 < len(argv):
            fit_json = argv[i + 1]
            i += 2
            continue
        if a.startswith("--fit="):
            fit_json = a.split("=", 1)[1]
        else:
            rest.append(a)
        i += 1
    positional = [a for a in rest if not a.startswith("-")]
    has_out = any(a == "--out" or a.startswith("--out=") for a in rest)
    if positional and not has_out and not any(a in ("-h", "--help") for a in rest):
        target = pathlib.Path(positional[0])
        name = target.stem if target.suffix else target.name
        rest += ["--out", str(pathlib.Path("results") / f"{name}-sensitivity")]
    sys.argv = [sys.argv[0]] + rest
    return main_wrapper("hdjax.sensitivity", __doc__, _run_with(fit_json))


if __name__ == "__main__":
    sys.exit(main())

"""The `hdjax` command: `hdjax fit|diagnose|sensitivity|tune TARGET [--out DIR] [options]`.

`python -m hdjax.fit` (and `.diagnose`, `.sensitivity`, `.tune`) call the same `main`. Every run
resolves its target, checks the whole config strictly (`hdjax._workflows.config.validate_config`), switches
on float64, writes `run.log` (every log line, timestamped) into the output folder and, beside the
command's `report.md`, a self-contained `report.html` (`hdjax._workflows.html`). Bad input ends with a
one-paragraph message and exit status 2.
"""

import argparse
import os
import pathlib
import sys
import textwrap
import warnings

COMMANDS = {
    "fit": (
        "identify the paper's model: regressions, joint trajectory-error fit, per-experiment fits",
        "fit.json, report.md, report.html, run.log, Fig. 3/4/5-style PNGs",
        "",
    ),
    "diagnose": (
        "find what the fitted model gets wrong and which SPEC §4 effect explains it",
        "diagnosis.json, extended_model.json, report.md, report.html, run.log, figures",
        "-diagnosis",
    ),
    "sensitivity": (
        "AD sensitivities, Fisher information, standard errors, the paper's section V ablations",
        "sensitivity.json, report.md, report.html, run.log, figures",
        "-sensitivity",
    ),
    "tune": (
        "tune a PI(D) torque controller with friction feed-forward through the identified plant",
        "tune.json, report.md, report.html, run.log, figures",
        "-tune",
    ),
}

_TARGET_HELP = (
    "a config YAML (naming a dataset folder, plus options by section) or a dataset folder (SPEC §2) "
    "or its dataset.yaml"
)


def default_out(command: str, target: str) -> pathlib.Path:
    """`results/<target name><suffix>`: `results/hd2` for `fit configs/hd2.yaml`,
    `results/hd2-diagnosis` for `diagnose`, `-sensitivity`, `-tune`."""
    t = pathlib.Path(target)
    name = t.stem if t.suffix else t.name
    if name == "dataset" and t.suffix:  # data/hd2/dataset.yaml -> hd2
        name = t.resolve().parent.name
    return pathlib.Path("results") / f"{name}{COMMANDS[command][2]}"


class _ConfigHelpParser(argparse.ArgumentParser):
    """Adds the config-file options of the command (and their defaults) to `--help`, importing the
    workflows only when help is asked for."""

    config_sections: tuple[str, ...] = ()

    def format_help(self) -> str:
        text = super().format_help()
        if not self.config_sections:
            return text
        from .config import NESTED, all_defaults

        defaults = all_defaults()
        lines = ["", "config file options (section: key = default); an unknown key is an error:"]
        for sec in self.config_sections:
            for k, v in defaults[sec].items():
                if k in NESTED.get(sec, ()):
                    for kk, vv in v.items():
                        lines.append(f"  {sec}.{k}.{kk} = {vv!r}")
                else:
                    lines.append(f"  {sec}.{k} = {v!r}")
        return text + "\n".join(lines) + "\n"


def build_parser() -> argparse.ArgumentParser:
    """The argparse parser of `hdjax` with one subcommand per workflow."""
    parser = argparse.ArgumentParser(
        prog="hdjax",
        description="Harmonic-drive test-bench data to a differentiable model (Taghirad & Bélanger), with JAX.",
        epilog=textwrap.dedent("""\
            examples:
              hdjax fit configs/hd2.yaml
              hdjax diagnose data/hd2 --out results/hd2-diagnosis
              hdjax sensitivity configs/hd2.yaml --fit results/hd2/fit.json
              hdjax tune configs/hd2.yaml --quiet
            'hdjax COMMAND --help' lists a command's options and its config-file options with their defaults."""),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    from .. import __version__

    parser.add_argument("--version", action="version", version=f"hdjax {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=_ConfigHelpParser)
    sections = {"fit": ("fit",), "diagnose": ("fit", "diagnose"), "sensitivity": ("fit", "sensitivity"),
                "tune": ("fit", "tune")}
    for name, (summary, writes, suffix) in COMMANDS.items():
        p = sub.add_parser(
            name,
            help=summary,
            description=f"hdjax {name}: {summary}. Writes {writes}.",
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        p.config_sections = sections[name]
        p.add_argument("target", metavar="TARGET", help=_TARGET_HELP)
        p.add_argument("--out", metavar="DIR", default=None,
                       help=f"output folder (default: results/<TARGET name>{suffix})")
        p.add_argument("--quiet", "-q", action="store_true", default=False,
                       help="print nothing but errors; run.log is still written (default: off)")
        if name == "sensitivity":
            p.add_argument("--fit", metavar="FIT_JSON", default=None,
                           help="parameter values from this fit.json (default: config `sensitivity.fit_json`, else "
                                "results/<TARGET name>/fit.json when it belongs to the dataset, else the paper's "
                                "regressions)")
        if name == "tune":
            p.add_argument("--fit", metavar="FIT_JSON", default=None,
                           help="identified plant from this fit.json (default: config `tune.fit`, else DIR/fit.json, "
                                "else results/<dataset>/fit.json, else the paper's regressions)")
    return parser


def _run_command(command: str, dataset, config: dict, out: pathlib.Path, log) -> None:
    from .friction import is_friction_only

    if command == "fit":
        if is_friction_only(dataset):
            from .friction import run_fit as run
        else:
            from .fit import run_fit as run
    elif command == "diagnose":
        if is_friction_only(dataset):
            from .friction import run_diagnose as run
        else:
            from .diagnose import run_diagnose as run
    elif command == "sensitivity":
        from .sensitivity import run_sensitivity as run
    else:
        from .tune import run_tune as run
    run(dataset, config, out, log=log)


def read_target(target: str):
    """`resolve_target(target)` for a command: (dataset, config dict, notes). What the reader
    accepts but ignores (extra CSV columns, unknown keys: `DatasetWarning`) comes back as `notes`,
    each message once, for the command to say as a plain `warning:` line on stderr and in run.log,
    instead of a Python warning that points into the command's own file; other warnings pass on."""
    from .._data.load import DatasetWarning, resolve_target

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DatasetWarning)
        dataset, config = resolve_target(target)
    notes = list(dict.fromkeys(str(w.message) for w in caught if issubclass(w.category, DatasetWarning)))
    for w in caught:
        if not issubclass(w.category, DatasetWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return dataset, dict(config or {}), notes


def main(argv: list[str] | None = None) -> int:
    """Run `hdjax COMMAND TARGET [options]`; `argv` without the program name (default:
    `sys.argv[1:]`). Returns the exit status: 0 done, 2 bad input."""
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")  # silence XLA's C++ log chatter
    args = build_parser().parse_args(sys.argv[1:] if argv is None else list(argv))
    command = args.command
    prog = f"hdjax {command}"

    import jax

    from .._plant.sharding import use_compilation_cache, use_host_devices

    use_host_devices()  # every CPU core simulates its share of the experiments
    jax.config.update("jax_enable_x64", True)
    use_compilation_cache()  # a later run reads back what this one compiles
    from .._data.load import DatasetError
    from .config import ConfigError, validate_config
    from .html import write_report_html
    from .progress import RunLog

    try:
        dataset, config, notes = read_target(args.target)
        validate_config(config, source=f"{args.target}")
    except (DatasetError, ConfigError) as e:
        print(f"{prog}: bad input: {e}", file=sys.stderr)
        return 2
    if getattr(args, "fit", None):
        key = "fit_json" if command == "sensitivity" else "fit"
        config[command] = dict(config.get(command) or {}, **{key: args.fit})
    out = pathlib.Path(args.out) if args.out else default_out(command, args.target)
    with RunLog(quiet=args.quiet, path=out / "run.log") as log:
        log._write(f"{prog} {args.target} --out {out}")
        for note in notes:
            log.warning(f"{prog}: warning: {note}")
        try:
            _run_command(command, dataset, config, out, log)
        except (DatasetError, ValueError) as e:
            log.error(f"{prog}: cannot run on {args.target}: {e}")
            return 2
        report = out / "report.md"
        if report.is_file():
            html = write_report_html(report)
            log(f"wrote {html}")
    return 0


def command_main(command: str):
    """`main` for `python -m hdjax.<command>`: the same as `hdjax <command> ...`."""

    def run(argv: list[str] | None = None) -> int:
        return main([command, *(sys.argv[1:] if argv is None else argv)])

    run.__doc__ = f"`python -m hdjax.{command} TARGET [options]`, the same as `hdjax {command} TARGET [options]`."
    return run

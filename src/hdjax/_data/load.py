"""Measured data on disk: a dataset folder (`dataset.yaml` + one CSV per experiment), configs.

The contract is SPEC.md section 2. A dataset folder looks like

```
my-rig/
  dataset.yaml      # name, drive constants, list of experiments (file, mode, start_time)
  locked_01.csv     # one experiment per CSV, header row, uniform time step, SI units
  free_01.csv
  truth.yaml        # optional, free-form (e.g. the virtual rig's true parameters)
```

- `load_dataset(folder_or_yaml)` reads and validates it into a `Dataset`;
- `write_dataset(...)` (`hdjax._data.write`) writes one (atomically, file by file);
- `load_config(path)` reads a config YAML that names a dataset folder plus options;
- `resolve_target(target)` turns a command's `TARGET` (folder, dataset.yaml or config) into
  `(Dataset, config)`.

Every bad input raises `DatasetError` (a `ValueError`) with a one-paragraph message naming the
file, the line / column / field and what to change. Nothing is resampled, dropped or clipped;
extra CSV columns are ignored with one warning per file.
"""

from __future__ import annotations

import csv
import dataclasses
import difflib
import math
import os
import pathlib
import re
import sys
import typing
import warnings
from typing import Any, NamedTuple

import numpy as np
import yaml

from .._model.paper import Drive
from .experiment import MODES, make_experiment, make_friction_experiment

__all__ = [
    "COLUMNS",
    "DatasetError",
    "Dataset",
    "load_config",
    "load_dataset",
    "resolve_target",
]

DATASET_FILE = "dataset.yaml"
TRUTH_FILE = "truth.yaml"

#: CSV columns per mode: `(required, optional)`, SI units (see SPEC.md section 2).
COLUMNS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "constrained": (("time", "current", "motor_velocity", "torque"), ("output_position", "motor_position")),
    "free": (("time", "current", "motor_velocity", "torque", "output_position"), ("motor_position",)),
    "friction": (("time", "velocity", "friction_torque"), ("position",)),
}
_UNITS = {
    "time": "s",
    "current": "A",
    "motor_velocity": "rad/s",
    "torque": "N·m",
    "output_position": "rad",
    "motor_position": "rad",
    "velocity": "rad/s",
    "friction_torque": "N·m",
    "position": "rad",
}
_TOP_KEYS = ("name", "drive", "experiments")
_DRIVE_KEYS = ("gear_ratio", "torque_constant", "load_inertia")
_ENTRY_KEYS = ("file", "mode", "start_time")
_MAX_JITTER = 0.01  # relative time-step jitter allowed, |dt - median dt| / median dt


class DynamicPart(NamedTuple):
    """A dataset's constrained and free experiments, as `Dataset.dynamic_part` returns them."""

    drive: Drive
    experiments: list
    files: list[str]
    modes: list[str]


class DatasetError(ValueError):
    """Bad dataset, CSV or config input. The message is one paragraph naming the file, the line,
    column or field, what is wrong and what to change."""


@typing.no_type_check  # not wrapped by the runtime type checker: frame 1 must be the warning function
def _caller_level() -> int:
    """`stacklevel` for a `warnings.warn` in the function that calls this, so that the warning points
    at the first frame outside hdjax (the code that called `load_dataset`), however deep the call
    and whatever wrappers lie between (the test suite's runtime type checker adds a frame per call)."""
    frame, level = sys._getframe(1), 1
    while frame is not None and (frame.f_globals.get("__name__", "").split(".")[0] in ("hdjax", "jaxtyping", "beartype")
                                 or frame.f_code.co_filename.startswith("<@beartype")):
        frame, level = frame.f_back, level + 1
    return level


class DatasetWarning(UserWarning):
    """Input that is accepted but partly ignored (extra CSV columns, unknown YAML keys)."""


# ----------------------------------------------------------------------------------------------
# Dataset
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class Dataset:
    """A loaded dataset folder.

    **Attributes:**

    - `name`: free text from `dataset.yaml` (the folder name when absent).
    - `folder`: absolute path of the folder holding `dataset.yaml`.
    - `drive`: the drive constants, `None` for a friction-only dataset without a `drive` block.
      `load_inertia` is 0.0 when not given (allowed only without free-motion experiments).
    - `experiments`: `Experiment` (constrained / free) or `FrictionExperiment`, in YAML order.
    - `files`: each experiment's CSV path as written in `dataset.yaml` (relative to `folder`).
    - `modes`: "constrained", "free" or "friction" per experiment.
    - `start_times`: s since the session began, 0.0 when not given.
    - `truth`: contents of an optional `truth.yaml` next to `dataset.yaml`, else `None`.
    """

    name: str
    folder: pathlib.Path
    drive: Drive | None
    experiments: list
    files: list[str]
    modes: list[str]
    start_times: list[float]
    truth: dict | None = None

    def __len__(self) -> int:
        return len(self.experiments)

    def indices(self, mode: str) -> list[int]:
        """Indices of the experiments of `mode` ("constrained", "free" or "friction")."""
        if mode not in MODES:
            raise ValueError(f"`Dataset.indices`: mode must be one of {list(MODES)}, got {mode!r}.")
        return [i for i, m in enumerate(self.modes) if m == mode]

    def dynamic_indices(self) -> list[int]:
        """Indices of the constrained and free-motion experiments (those a simulation can replay)."""
        return [i for i, m in enumerate(self.modes) if m in ("constrained", "free")]

    def dynamic_part(self, command: str, *, at_least: int = 1) -> DynamicPart:
        """The constrained and free experiments (with their files and modes) and the drive that
        `command` simulates; a `DatasetError` naming the folder and the fix when there is no
        `drive` block or fewer than `at_least` such experiments."""
        idx = self.dynamic_indices()
        if self.drive is None or len(idx) < at_least:
            have = ", ".join(f"{self.modes.count(m)} {m}" for m in sorted(set(self.modes))) or "no"
            no_drive = " and no `drive` block" if self.drive is None else ""
            hint = (" Friction-only datasets are fitted and diagnosed as friction by `hdjax fit` and `hdjax diagnose`."
                    if set(self.modes) == {"friction"} else "")
            raise DatasetError(
                f"{self.folder / 'dataset.yaml'}: `{command}` needs at least {at_least} constrained or free "
                f"experiment{'s' if at_least > 1 else ''} and a `drive` block; this dataset has {have} experiments"
                f"{no_drive}. Add such records (and the drive constants) to dataset.yaml.{hint}")
        return DynamicPart(self.drive, [self.experiments[i] for i in idx], [self.files[i] for i in idx],
                           [self.modes[i] for i in idx])

    def friction_indices(self) -> list[int]:
        """Indices of the friction experiments."""
        return self.indices("friction")


# ----------------------------------------------------------------------------------------------
# YAML with line numbers, YAML 1.2 floats and no silently overwritten duplicate keys
# ----------------------------------------------------------------------------------------------


class _Map(dict):
    """A dict that remembers the YAML line (1-based) of itself and of each key."""

    line: int | None = None
    lines: dict

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.lines = {}


class _Loader(yaml.SafeLoader):
    pass


def _construct_mapping(loader: _Loader, node: yaml.MappingNode, deep: bool = False) -> _Map:
    loader.flatten_mapping(node)
    out = _Map()
    out.line = node.start_mark.line + 1
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        try:
            duplicate = key in out
        except TypeError as e:
            raise yaml.constructor.ConstructorError(
                "while constructing a mapping", node.start_mark, "found an unhashable key", key_node.start_mark
            ) from e
        if duplicate:
            raise yaml.constructor.ConstructorError(
                "while constructing a mapping",
                node.start_mark,
                f"found duplicate key {key!r} (the earlier value would be silently lost)",
                key_node.start_mark,
            )
        out[key] = loader.construct_object(value_node, deep=deep)
        out.lines[key] = key_node.start_mark.line + 1
    return out


_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)
# YAML 1.1 (PyYAML) reads `1e-3` as a string; accept YAML 1.2 floats such as 1e-3 and 5E+2.
_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)


def _plain(obj: Any) -> Any:
    """Recursively turn `_Map` into plain dicts."""
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_plain(v) for v in obj]
    return obj


def _read_yaml(path: pathlib.Path, what: str) -> Any:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise dataset_error(path, None, f"{what} does not exist", "Check the path.") from None
    except (OSError, UnicodeDecodeError) as e:
        raise dataset_error(path, None, f"{what} cannot be read ({e})", "Make it a readable UTF-8 text file.") from None
    try:
        return yaml.load(text, Loader=_Loader)
    except yaml.MarkedYAMLError as e:
        mark = e.problem_mark or e.context_mark
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark is not None else None
        problem = " ".join(str(x) for x in (e.context, e.problem) if x)
        raise dataset_error(
            path, where, f"YAML syntax error: {problem}", "Fix the YAML there (indentation, `key: value` pairs, quotes)."
        ) from None
    except yaml.YAMLError as e:
        raise dataset_error(path, None, f"YAML syntax error: {e}", "Fix the YAML syntax.") from None


# ----------------------------------------------------------------------------------------------
# Messages
# ----------------------------------------------------------------------------------------------


def dataset_error(path, where: str | None, what: str, fix: str) -> DatasetError:
    """The one form of every dataset message, reading and writing alike (`hdjax._data.write`):
    `path[, where]: what. fix`, on one line."""
    loc = str(path) + (f", {where}" if where else "")
    msg = f"{loc}: {what}. {fix}"
    return DatasetError(" ".join(msg.split()))


def _yaml_where(mapping: Any, key: str | None, field: str) -> str:
    """`line N (`field`)` for a key of a `_Map`, or just the field."""
    line = None
    if isinstance(mapping, _Map):
        line = mapping.lines.get(key, mapping.line) if key is not None else mapping.line
    return f"line {line} (`{field}`)" if line is not None else f"`{field}`"


def _did_you_mean(word: str, candidates) -> str:
    match = difflib.get_close_matches(word, [str(c) for c in candidates], n=1, cutoff=0.6)
    return f" (did you mean `{match[0]}`?)" if match else ""


def _misspelled(expected: str, present) -> str:
    """For a missing key or column: point at a present one that looks like a misspelling of it."""
    match = difflib.get_close_matches(expected, [str(c) for c in present], n=1, cutoff=0.6)
    return f" (found `{match[0]}`: did you mean `{expected}`?)" if match else ""


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


# ----------------------------------------------------------------------------------------------
# Loading
# ----------------------------------------------------------------------------------------------


def _dataset_yaml_path(folder_or_yaml) -> pathlib.Path:
    p = pathlib.Path(folder_or_yaml).expanduser()
    if p.is_dir():
        y = p / DATASET_FILE
        if not y.is_file():
            raise dataset_error(
                y,
                None,
                f"no `{DATASET_FILE}` in the dataset folder",
                f"Put a `{DATASET_FILE}` (name, drive, experiments; see SPEC.md section 2) in {p}, "
                "or pass the path of the dataset YAML itself.",
            )
        return y.resolve()
    if not p.exists():
        raise dataset_error(p, None, "dataset folder or YAML does not exist", "Check the path.")
    return p.resolve()


def _drive_number(doc: dict, key: str, yaml_path, *, required: bool, positive: bool, why: str) -> float | None:
    unit = {"gear_ratio": "N, -", "torque_constant": "Km, N·m/A", "load_inertia": "Jload, kg·m²"}[key]
    drive = doc["drive"]
    if key not in drive:
        if required:
            raise dataset_error(
                yaml_path,
                _yaml_where(doc, "drive", "drive"),
                f"`drive.{key}` ({unit}) is missing{_misspelled(key, [k for k in drive if k not in _DRIVE_KEYS])}; "
                f"it is required {why}",
                f"Add `{key}: <positive number>` to the `drive` block.",
            )
        return None
    v = drive[key]
    if not _is_number(v) or (positive and v <= 0) or (not positive and v < 0):
        need = "a positive" if positive else "a non-negative"
        raise dataset_error(
            yaml_path,
            _yaml_where(drive, key, f"drive.{key}"),
            f"`drive.{key}` ({unit}) is {v!r}, not {need} finite number" + (f" (required {why})" if positive else ""),
            f"Set `{key}` to {need} number in SI units.",
        )
    return float(v)


def _parse_drive(doc: dict, yaml_path, modes: list[str]) -> Drive | None:
    dynamic = [m for m in modes if m in ("constrained", "free")]
    if "drive" not in doc or doc["drive"] is None:
        if dynamic:
            raise dataset_error(
                yaml_path,
                "`drive`" + _misspelled("drive", [k for k in doc if k not in _TOP_KEYS]),
                f"the `drive` block is missing but the dataset has {dynamic[0]} experiments",
                "Add `drive:` with `gear_ratio` (N), `torque_constant` (Km, N·m/A) and, for free-motion "
                "experiments, `load_inertia` (Jload, kg·m²). Only friction-only datasets may omit it.",
            )
        return None
    drive = doc["drive"]
    if not isinstance(drive, dict):
        raise dataset_error(
            yaml_path,
            _yaml_where(doc, "drive", "drive"),
            f"`drive` must be a mapping, got {type(drive).__name__} {drive!r}",
            "Write `drive:` followed by indented `gear_ratio: ...`, `torque_constant: ...`, `load_inertia: ...`.",
        )
    unknown = [k for k in drive if k not in _DRIVE_KEYS]
    if unknown:
        hints = ", ".join(f"`{k}`{_did_you_mean(str(k), _DRIVE_KEYS)}" for k in unknown)
        warnings.warn(
            f"{yaml_path}: ignoring unknown key(s) in the `drive` block: {hints}; known keys are {list(_DRIVE_KEYS)}.",
            DatasetWarning,
            stacklevel=_caller_level(),  # the caller of `load_dataset`
        )
    why = "because the dataset has constrained or free-motion experiments"
    gear = _drive_number(doc, "gear_ratio", yaml_path, required=bool(dynamic), positive=True, why=why)
    km = _drive_number(doc, "torque_constant", yaml_path, required=bool(dynamic), positive=True, why=why)
    has_free = "free" in modes
    why_j = "because the dataset has free-motion experiments"
    jload = _drive_number(doc, "load_inertia", yaml_path, required=has_free, positive=has_free, why=why_j)
    if gear is None or km is None:
        return None  # friction-only dataset with an incomplete drive block: constants unused
    return Drive(gear_ratio=gear, torque_constant=km, load_inertia=0.0 if jload is None else jload)


def resolve_member(folder: pathlib.Path, file: str, yaml_path, where: str) -> pathlib.Path:
    """`folder/file`, refusing absolute paths and paths that escape `folder` (checked on the
    normalised path, so symlinked data files inside the folder are fine)."""
    rel = pathlib.PurePath(file)
    if rel.is_absolute() or pathlib.PureWindowsPath(file).is_absolute() or file.startswith("~"):
        raise dataset_error(
            yaml_path,
            where,
            f"file `{file}` is an absolute path",
            "Give the CSV path relative to the folder holding dataset.yaml, and keep the CSV inside that folder.",
        )
    full = pathlib.Path(os.path.normpath(folder / rel))
    try:
        full.relative_to(folder)
    except ValueError:
        raise dataset_error(
            yaml_path,
            where,
            f"file `{file}` resolves to {full}, outside the dataset folder {folder}",
            "Move the CSV into the dataset folder (or a subfolder) and give its path relative to dataset.yaml.",
        ) from None
    if full == folder:
        raise dataset_error(yaml_path, where, f"file `{file}` names the dataset folder itself", "Name a CSV file.")
    return full


def load_dataset(folder_or_yaml: str | os.PathLike) -> Dataset:
    """Load and validate a dataset folder (SPEC.md section 2).

    **Arguments:**

    - `folder_or_yaml`: the folder holding `dataset.yaml`, or the path of the dataset YAML.

    **Returns:** a `Dataset`. Raises `DatasetError` on any bad input; warns (`DatasetWarning`)
    once per CSV that has extra columns, which are ignored.
    """
    yaml_path = _dataset_yaml_path(folder_or_yaml)
    folder = yaml_path.parent
    doc = _read_dataset_doc(yaml_path)
    entries = _experiment_entries(doc, yaml_path)

    modes, files, starts, paths = [], [], [], []
    seen: dict[pathlib.Path, int] = {}
    for i, entry in enumerate(entries):
        file, mode, start, path = _parse_entry(doc, i, entry, folder, yaml_path, seen)
        modes.append(mode)
        files.append(file)
        starts.append(float(start))
        paths.append(path)

    drive = _parse_drive(doc, yaml_path, modes)

    experiments = []
    for path, mode, start in zip(paths, modes, starts):
        cols = _read_csv(path, mode)
        experiments.append(_experiment_from_columns(cols, mode, start))

    name = doc.get("name")
    return Dataset(
        name=folder.name if name is None else str(name),
        folder=folder,
        drive=drive,
        experiments=experiments,
        files=files,
        modes=modes,
        start_times=starts,
        truth=_read_truth(folder),
    )


def _read_dataset_doc(yaml_path: pathlib.Path) -> dict:
    """The dataset YAML's top-level mapping; warns about unknown top-level keys that look like
    misspelled known ones."""
    doc = _read_yaml(yaml_path, "dataset YAML")
    if not isinstance(doc, dict):
        raise dataset_error(
            yaml_path,
            None,
            f"the top level must be a mapping with `name`, `drive` and `experiments`, got {type(doc).__name__}",
            "Write `name: ...`, `drive:` and `experiments:` at the top level (see SPEC.md section 2).",
        )
    for k in doc:
        if k not in _TOP_KEYS and _did_you_mean(str(k), _TOP_KEYS):
            warnings.warn(
                f"{yaml_path}: ignoring unknown top-level key `{k}`{_did_you_mean(str(k), _TOP_KEYS)}.",
                DatasetWarning,
                stacklevel=_caller_level(),  # the caller of `load_dataset`
            )
    return doc


def _experiment_entries(doc: dict, yaml_path: pathlib.Path) -> list:
    """The `experiments` list, refused when missing, not a list or empty."""
    if "experiments" not in doc:
        raise dataset_error(
            yaml_path,
            "`experiments`" + _misspelled("experiments", [k for k in doc if k not in _TOP_KEYS]),
            "the `experiments` list is missing",
            "Add `experiments:` with one `- file: <csv>` / `mode: constrained|free|friction` entry per CSV.",
        )
    entries = doc["experiments"]
    if not isinstance(entries, list):
        raise dataset_error(
            yaml_path,
            _yaml_where(doc, "experiments", "experiments"),
            f"`experiments` must be a list, got {type(entries).__name__}",
            "Write each experiment as a list item `- file: <csv>` with `mode: ...` under it.",
        )
    if not entries:
        raise dataset_error(
            yaml_path,
            _yaml_where(doc, "experiments", "experiments"),
            "the `experiments` list is empty",
            "Add at least one `- file: <csv>` / `mode: ...` entry.",
        )
    return entries


def _parse_entry(doc: dict, i: int, entry, folder: pathlib.Path, yaml_path: pathlib.Path, seen: dict):
    """Experiment entry `i`: its `file`, `mode`, `start_time` (s, 0 when absent) and resolved CSV
    path, which must exist, lie inside `folder` and not be listed twice (`seen`: path → entry,
    updated); warns about unknown keys."""
    field = f"experiments[{i}]"
    if not isinstance(entry, dict):
        raise dataset_error(
            yaml_path,
            _yaml_where(doc, "experiments", field),
            f"experiment entry {i} is {entry!r}, not a mapping",
            "Write each entry as `- file: <csv>` followed by `mode: constrained|free|friction`.",
        )
    unknown = [k for k in entry if k not in _ENTRY_KEYS]
    if unknown:
        hints = ", ".join(f"`{k}`{_did_you_mean(str(k), _ENTRY_KEYS)}" for k in unknown)
        warnings.warn(
            f"{yaml_path}, {_yaml_where(entry, unknown[0], field)}: ignoring unknown key(s) {hints}; "
            f"known keys are {list(_ENTRY_KEYS)}.",
            DatasetWarning,
            stacklevel=_caller_level(),  # the caller of `load_dataset`
        )
    for key, fix in (
        ("file", "Add `file: <csv path relative to dataset.yaml>`."),
        ("mode", f"Add `mode:` with one of {', '.join(MODES)}."),
    ):
        if key not in entry or entry[key] is None:
            raise dataset_error(
                yaml_path,
                _yaml_where(entry, None, f"{field}.{key}"),
                f"experiment entry {i} has no `{key}`{_misspelled(key, unknown)}",
                fix,
            )
    file, mode = entry["file"], entry["mode"]
    _check_file_and_mode(file, mode, entry, field, yaml_path)
    start = entry.get("start_time", 0.0)
    if start is None:
        start = 0.0
    if not _is_number(start) or start < 0:
        raise dataset_error(
            yaml_path,
            _yaml_where(entry, "start_time", f"{field}.start_time"),
            f"`start_time` is {start!r}, not a finite non-negative number",
            "Give the seconds since the session began (e.g. `start_time: 120.0`), or leave it out for 0.",
        )
    path = _entry_path(folder, file, entry, field, yaml_path, seen)
    seen[path] = i
    return file, mode, start, path


def _check_file_and_mode(file, mode, entry: dict, field: str, yaml_path: pathlib.Path) -> None:
    """Refuse a `file` that is not a non-empty string and a `mode` outside `MODES`."""
    if not isinstance(file, str) or not file.strip():
        raise dataset_error(
            yaml_path,
            _yaml_where(entry, "file", f"{field}.file"),
            f"`file` must be a non-empty path string, got {file!r}",
            "Give the CSV path relative to dataset.yaml.",
        )
    if mode not in MODES:
        raise dataset_error(
            yaml_path,
            _yaml_where(entry, "mode", f"{field}.mode"),
            f"unknown mode {mode!r}{_did_you_mean(str(mode), MODES)}",
            f"Use one of: {', '.join(MODES)}.",
        )


def _entry_path(folder: pathlib.Path, file: str, entry: dict, field: str, yaml_path: pathlib.Path, seen: dict):
    """The CSV path of an entry, inside `folder`, listed once (`seen`) and existing."""
    path = resolve_member(folder, file, yaml_path, _yaml_where(entry, "file", f"{field}.file"))
    if path in seen:
        raise dataset_error(
            yaml_path,
            _yaml_where(entry, "file", f"{field}.file"),
            f"file `{file}` is listed twice (also as experiments[{seen[path]}])",
            "List each CSV once; copy the file if you really mean to use the same record twice.",
        )
    if not path.is_file():
        raise dataset_error(
            path,
            f"named in {yaml_path} {_yaml_where(entry, 'file', f'{field}.file')}",
            "the CSV file does not exist",
            "Fix the `file` path (relative to dataset.yaml) or add the file.",
        )
    return path


def _experiment_from_columns(cols: dict[str, np.ndarray], mode: str, start: float):
    """An `Experiment` (friction or dynamic, by `mode`) from a CSV's SI columns, starting at `start` (s)."""
    if mode == "friction":
        return make_friction_experiment(
            cols["time"], cols["velocity"], cols["friction_torque"], position=cols.get("position"), start_time=start
        )
    return make_experiment(
        cols["time"],
        cols["current"],
        cols["torque"],
        cols["motor_velocity"],
        mode=mode,
        output_position=cols.get("output_position"),
        motor_position=cols.get("motor_position"),
        start_time=start,
    )


def _read_truth(folder: pathlib.Path) -> dict | None:
    """The folder's truth.yaml as plain Python values, or None when there is none (or it is empty)."""
    truth = None
    truth_path = folder / TRUTH_FILE
    if truth_path.is_file():
        truth = _read_yaml(truth_path, "truth YAML")
        if truth is not None and not isinstance(truth, dict):
            raise dataset_error(
                truth_path,
                None,
                f"the top level must be a mapping, got {type(truth).__name__}",
                "Write `key: value` pairs at the top level, or remove truth.yaml.",
            )
        truth = _plain(truth) if truth is not None else None
    return truth


# ----------------------------------------------------------------------------------------------
# CSV
# ----------------------------------------------------------------------------------------------


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def _read_csv(path: pathlib.Path, mode: str) -> dict[str, np.ndarray]:
    """Read one experiment CSV; returns the required and present optional columns as float64."""
    required, _ = COLUMNS[mode]
    header, header_line, rows, lines = _csv_rows(path)
    if header is None:
        raise dataset_error(path, None, "the CSV is empty", f"Write a header row ({', '.join(required)}) and the samples.")
    names = [h.strip() for h in header]
    used = _check_header(path, names, header_line, mode)
    data = _parse_cells(path, rows, lines, names, used)
    cols = {n: data[:, c] for c, n in enumerate(used)}
    check_time(path, cols["time"], lines)
    return cols


def _csv_rows(path: pathlib.Path) -> tuple[list[str] | None, int, list[list[str]], list[int]]:
    """The header row (None if the file has no row), its line number, and the data rows with their
    line numbers; blank lines are skipped."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(f)
            header = None
            header_line = 0  # set with `header`
            rows: list[list[str]] = []
            lines: list[int] = []
            for row in reader:
                if not row or (len(row) == 1 and not row[0].strip()):
                    continue  # blank line: no data in it
                if header is None:
                    header = row
                    header_line = reader.line_num
                    continue
                rows.append(row)
                lines.append(reader.line_num)
    except UnicodeDecodeError as e:
        raise dataset_error(path, None, f"not UTF-8 text ({e})", "Save the CSV as UTF-8 (or plain ASCII).") from None
    except csv.Error as e:
        # csv.Error comes only from reading rows, so `reader` is bound
        line = f"line {reader.line_num}"  # pyright: ignore[reportPossiblyUnboundVariable]
        raise dataset_error(path, line, f"malformed CSV ({e})", "Fix the quoting on that line.") from None
    except OSError as e:
        raise dataset_error(path, None, f"cannot be read ({e})", "Check the file's permissions.") from None
    return header, header_line, rows, lines


def _check_header(path: pathlib.Path, names: list[str], header_line: int, mode: str) -> list[str]:
    """The header's columns that `mode` uses, in file order; refuses a missing, nameless, duplicate
    or missing required column and warns about columns it ignores."""
    required, optional = COLUMNS[mode]
    if all(_is_float(h) for h in names):
        raise dataset_error(
            path,
            f"line {header_line}",
            "there is no header row (the first line holds numbers)",
            f"Add a header row naming the columns, e.g. `{','.join(required)}`.",
        )
    for j, n in enumerate(names):
        if not n:
            raise dataset_error(
                path,
                f"line {header_line}, column {j + 1}",
                "empty column name in the header",
                "Name every column (or remove the empty one).",
            )
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise dataset_error(
            path,
            f"line {header_line}, column(s) " + ", ".join(f"`{d}`" for d in dupes),
            "duplicate column name(s) in the header",
            "Rename or remove the duplicates so each column appears once.",
        )
    known = set(required) | set(optional)
    extra = [n for n in names if n not in known]
    _check_required_columns(path, names, header_line, mode, extra)
    if extra:
        hints = ", ".join(f"`{n}`{_did_you_mean(n, [o for o in optional if o not in names])}" for n in extra)
        warnings.warn(
            f"{path}: ignoring column(s) not used by {mode} experiments: {hints}.",
            DatasetWarning,
            stacklevel=_caller_level(),  # the caller of `load_dataset`
        )
    return [n for n in names if n in known]


def _check_required_columns(path: pathlib.Path, names: list[str], header_line: int, mode: str, extra: list[str]) -> None:
    """Refuse a header that lacks a column `mode` requires, naming its unit and a near miss in `extra`."""
    required, optional = COLUMNS[mode]
    missing = [n for n in required if n not in names]
    if missing:
        parts = [f"`{m}` ({_UNITS[m]}){_misspelled(m, extra)}" for m in missing]
        hint = ""
        if len(names) == 1 and any(c in names[0] for c in ";\t|"):
            hint = " The header looks like it uses a delimiter other than a comma; hdjax reads comma-separated files."
        raise dataset_error(
            path,
            f"line {header_line} (header)",
            f"{mode} experiments need column(s) {', '.join(parts)}, which the header lacks; "
            f"found {', '.join(f'`{n}`' for n in names)}",
            f"Rename or add the column(s); a {mode} CSV needs {', '.join(required)}"
            + (f" and may have {', '.join(optional)}" if optional else "")
            + "."
            + hint,
        )


def _parse_cells(path: pathlib.Path, rows: list[list[str]], lines: list[int], names: list[str], used: list[str]) -> np.ndarray:
    """The `used` columns of the data rows as float64 (row, column); refuses a row of the wrong
    length and an empty, non-numeric or non-finite cell, naming line and column."""
    index = {n: names.index(n) for n in used}
    data = np.empty((len(rows), len(used)))
    for r, (row, line) in enumerate(zip(rows, lines)):
        if len(row) != len(names):
            raise dataset_error(
                path,
                f"line {line}",
                f"the row has {len(row)} field(s) but the header has {len(names)}",
                "Give every row one value per header column (check for stray commas or decimal commas).",
            )
        for c, n in enumerate(used):
            cell = row[index[n]].strip()
            try:
                v = float(cell)
            except ValueError:
                what = "empty cell" if not cell else f"non-numeric value {cell!r}"
                raise dataset_error(
                    path,
                    f"line {line}, column `{n}`",
                    what,
                    f"Write a number in SI units ({_UNITS[n]}) with a '.' decimal point; "
                    "hdjax does not drop or fill in samples.",
                ) from None
            if not math.isfinite(v):
                raise dataset_error(
                    path,
                    f"line {line}, column `{n}`",
                    f"value {cell!r} is {'NaN' if math.isnan(v) else 'inf'}",
                    "Replace it with a measured value or cut the record into valid pieces; "
                    "hdjax does not drop or interpolate samples.",
                )
            data[r, c] = v
    return data


def check_time(path, time: np.ndarray, lines: list[int]) -> None:
    """At least 3 samples, strictly increasing, uniform step within `_MAX_JITTER`."""
    if len(time) < 3:
        raise dataset_error(
            path,
            "column `time`",
            f"only {len(time)} data row(s)",
            "Give at least 3 samples (a real record has many more).",
        )
    dt = np.diff(time)
    bad = np.flatnonzero(dt <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        raise dataset_error(
            path,
            f"line {lines[k]}, column `time`",
            f"time is not strictly increasing ({float(time[k - 1])!r} s on line {lines[k - 1]}, then {float(time[k])!r} s)",
            "Sort the rows by time and remove repeated samples; split separate records into separate files.",
        )
    step = float(np.median(dt))
    jitter = np.abs(dt - step) / step
    bad = np.flatnonzero(jitter > _MAX_JITTER)
    if bad.size:
        k = int(bad[0]) + 1
        raise dataset_error(
            path,
            f"line {lines[k]}, column `time`",
            f"uneven time step: {float(dt[k - 1])!r} s from line {lines[k - 1]}, against a median step of {step!r} s "
            f"({100 * jitter[k - 1]:.3g} % off; {bad.size} step(s) exceed the {100 * _MAX_JITTER:g} % tolerance)",
            "Resample the record onto a uniform grid yourself or split it at the gap into separate files; "
            "hdjax never resamples.",
        )


# ----------------------------------------------------------------------------------------------
# Configs and command targets
# ----------------------------------------------------------------------------------------------


def load_config(path: str | os.PathLike) -> dict:
    """Read a config YAML: a mapping with a `dataset:` key (folder path, relative to the config
    file's own folder) plus free-form options. Returns a plain dict with `dataset` resolved to an
    absolute `pathlib.Path` (its existence is not checked here)."""
    p = pathlib.Path(path).expanduser()
    if not p.is_file():
        raise dataset_error(p, None, "config file does not exist", "Check the path.")
    doc = _read_yaml(p, "config YAML")
    if not isinstance(doc, dict):
        raise dataset_error(
            p,
            None,
            f"the top level must be a mapping, got {type(doc).__name__}",
            "Write `dataset: <folder>` and the options as `key: value` pairs.",
        )
    if "dataset" not in doc or doc["dataset"] is None:
        raise dataset_error(
            p,
            "`dataset`" + _misspelled("dataset", list(doc)),
            "the config has no `dataset` key",
            "Add `dataset: <folder>` (relative to this config file's folder).",
        )
    ds = doc["dataset"]
    if not isinstance(ds, (str, os.PathLike)) or not str(ds).strip():
        raise dataset_error(
            p,
            _yaml_where(doc, "dataset", "dataset"),
            f"`dataset` must be a folder path string, got {ds!r}",
            "Write `dataset: <folder>` (relative to this config file's folder).",
        )
    out = _plain(doc)
    out["dataset"] = (p.resolve().parent / pathlib.Path(ds).expanduser()).resolve()
    return out


def resolve_target(target: str | os.PathLike) -> tuple[Dataset, dict]:
    """A command's `TARGET` to `(dataset, config)`: a dataset folder or a dataset YAML (one with
    `experiments`) gives `config = {}`; any other YAML is a config naming the dataset folder."""
    p = pathlib.Path(target).expanduser()
    if p.is_dir():
        return load_dataset(p), {}
    if not p.exists():
        raise dataset_error(p, None, "target does not exist", "Pass a dataset folder, its dataset.yaml, or a config YAML.")
    if p.suffix.lower() not in (".yaml", ".yml"):
        raise dataset_error(
            p,
            None,
            "target is neither a folder nor a .yaml/.yml file",
            "Pass a dataset folder, its dataset.yaml, or a config YAML.",
        )
    doc = _read_yaml(p, "YAML")
    if isinstance(doc, dict) and "experiments" in doc:
        return load_dataset(p), {}
    config = load_config(p)
    folder = config["dataset"]
    if not folder.exists():
        raise dataset_error(
            p,
            _yaml_where(doc, "dataset", "dataset"),
            f"the dataset folder {folder} does not exist",
            "Fix `dataset:` (a path relative to this config file's folder).",
        )
    return load_dataset(folder), config

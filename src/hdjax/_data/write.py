"""Writing a dataset folder (SPEC §2) that `hdjax.load_dataset` reads back: `write_dataset`.

Every file is written atomically (`hdjax._workflows.io.atomic_write_text`); `dataset.yaml` last, so a folder
with a `dataset.yaml` is complete. What the reader would refuse (NaN or inf, a bad time column, a
mode that disagrees with the experiment) is refused here before anything is written.
"""

import os
import pathlib
from typing import Any

import numpy as np
import yaml

from .._model.paper import Drive
from .._workflows.io import atomic_write_text
from .experiment import MODES, Experiment, FrictionExperiment
from .load import DATASET_FILE, TRUTH_FILE, DatasetError, check_time, dataset_error, resolve_member

__all__ = ["write_dataset"]


def _yaml_value(x: Any) -> Any:
    """Plain Python values for `yaml.safe_dump` (arrays to lists, numpy/JAX scalars to floats)."""
    if isinstance(x, dict):
        return {str(k): _yaml_value(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_yaml_value(v) for v in x]
    if x is None or isinstance(x, (str, bool)):
        return str(x) if isinstance(x, str) else x
    if isinstance(x, int):
        return int(x)
    if isinstance(x, float):
        return float(x)  # also np.float64, which the safe dumper refuses
    if isinstance(x, os.PathLike):
        return os.fspath(x)
    if hasattr(x, "to_dict"):
        return _yaml_value(x.to_dict())
    a = np.asarray(x)
    if a.ndim == 0:
        return a.item()
    return a.tolist()


def _csv_text(columns: dict[str, np.ndarray], digits: int | None = None) -> str:
    names = list(columns)
    data = np.column_stack([columns[n] for n in names])
    # repr() of a Python float is the shortest string that reads back to the same float.
    fmt = repr if digits is None else f"{{:.{int(digits)}g}}".format
    body = "\n".join(",".join(map(fmt, row)) for row in data.tolist())
    return ",".join(names) + "\n" + body + "\n"


def write_dataset(
    folder: str | os.PathLike,
    name: str,
    drive: Drive | None,
    experiments: list,
    modes: list[str],
    files: list[str],
    start_times: list[float] | None = None,
    truth: dict | None = None,
    digits: int | None = None,
) -> pathlib.Path:
    """Write a dataset folder that `load_dataset` reads back (exactly with the default `repr` floats).

    **Arguments:**

    - `folder`: the dataset folder (created if needed).
    - `name`: free text for `dataset.yaml`.
    - `drive`: drive constants; may be `None` only when every experiment is friction.
      `load_inertia` is written when positive (and must be, with free-motion experiments).
    - `experiments`: `Experiment` (constrained / free) or `FrictionExperiment`, unbatched;
      padding (`mask` False) is dropped.
    - `modes`: "constrained", "free" or "friction" per experiment, matching its type.
    - `files`: CSV paths relative to `folder`, unique.
    - `start_times`: s since the session began; default each experiment's `start_time`.
    - `truth`: optional free-form mapping written to `truth.yaml` (arrays become lists).
    - `digits`: significant digits of the CSV values (e.g. 7 for compact files); default `None`
      writes `repr` floats, which read back exactly.

    CSV columns: `time,current,motor_velocity,torque[,output_position][,motor_position]` for
    constrained / free (free always has `output_position`; the optional ones appear when measured),
    `time,velocity,friction_torque[,position]` for friction. Each file is written atomically
    (temporary name, then rename); `dataset.yaml` last. Returns the folder path.
    """
    folder = pathlib.Path(folder).expanduser().resolve()
    _check_write_counts(folder, experiments, modes, files, start_times)
    yaml_path = folder / DATASET_FILE
    targets = _write_targets(folder, yaml_path, experiments, modes, files)
    _check_write_drive(drive, modes, yaml_path)

    entries = []
    for i, (exp, mode, file, path) in enumerate(zip(experiments, modes, files, targets)):
        cols = _experiment_columns(exp, mode, i, yaml_path)
        _write_experiment_csv(path, cols, digits)
        start = float(exp.start_time) if start_times is None else float(start_times[i])
        entry: dict[str, Any] = {"file": file, "mode": mode}
        if start != 0.0:
            entry["start_time"] = start
        entries.append(entry)

    doc: dict[str, Any] = {"name": str(name)}
    if drive is not None:
        d = {"gear_ratio": float(drive.gear_ratio), "torque_constant": float(drive.torque_constant)}
        if float(drive.load_inertia) > 0:
            d["load_inertia"] = float(drive.load_inertia)
        doc["drive"] = d
    doc["experiments"] = entries
    if truth is not None:
        atomic_write_text(folder / TRUTH_FILE, yaml.safe_dump(_yaml_value(truth), sort_keys=False, allow_unicode=True))
    atomic_write_text(yaml_path, yaml.safe_dump(doc, sort_keys=False, allow_unicode=True))
    return folder


def _check_write_counts(folder: pathlib.Path, experiments: list, modes: list, files: list, start_times) -> None:
    """Refuse mismatched counts of experiments, modes, files and start times, and no experiments."""
    n = len(experiments)
    if len(modes) != n or len(files) != n or (start_times is not None and len(start_times) != n):
        raise DatasetError(
            f"`write_dataset` ({folder}): got {n} experiments, {len(modes)} modes, {len(files)} files"
            + (f", {len(start_times)} start times" if start_times is not None else "")
            + "; give one of each per experiment."
        )
    if n == 0:
        raise DatasetError(f"`write_dataset` ({folder}): no experiments given; a dataset needs at least one.")


def _write_targets(folder: pathlib.Path, yaml_path: pathlib.Path, experiments: list, modes: list, files: list) -> list:
    """The CSV path of each experiment, after checking its mode against its type and `free` flag
    and its file name (non-empty, inside `folder`, given once)."""
    targets = []
    for i, (exp, mode, file) in enumerate(zip(experiments, modes, files)):
        where = f"`files[{i}]`"
        if mode not in MODES:
            raise dataset_error(yaml_path, f"`modes[{i}]`", f"unknown mode {mode!r}", f"Use one of: {', '.join(MODES)}.")
        want = FrictionExperiment if mode == "friction" else Experiment
        if not isinstance(exp, want):
            raise dataset_error(
                yaml_path,
                f"`experiments[{i}]`",
                f"mode {mode!r} needs a {want.__name__}, got {type(exp).__name__}",
                "Pass matching experiments and modes.",
            )
        if mode != "friction" and isinstance(exp, Experiment) and (float(exp.free) == 1.0) != (mode == "free"):
            raise dataset_error(
                yaml_path,
                f"`modes[{i}]`",
                f"mode {mode!r} disagrees with the experiment's `free` flag {float(exp.free)}",
                "Pass the mode the experiment was built with.",
            )
        if not isinstance(file, str) or not file.strip():
            raise dataset_error(yaml_path, where, f"file name {file!r} is not a non-empty string", "Give a relative path.")
        path = resolve_member(folder, file, yaml_path, where)
        if path in targets:
            raise dataset_error(yaml_path, where, f"file `{file}` is given twice", "Give each experiment its own file.")
        targets.append(path)
    return targets


def _check_write_drive(drive: Drive | None, modes: list[str], yaml_path: pathlib.Path) -> None:
    """Refuse a missing drive with constrained or free experiments, and a load inertia (kg·m²) that
    is not positive with free ones."""
    if drive is None and any(m != "friction" for m in modes):
        raise DatasetError(
            f"`write_dataset` ({yaml_path}): `drive` is None but there are constrained or free experiments; "
            "pass a `Drive`."
        )
    if drive is not None and "free" in modes and not float(drive.load_inertia) > 0:
        raise DatasetError(
            f"`write_dataset` ({yaml_path}): `drive.load_inertia` is {float(drive.load_inertia)!r} but there are "
            "free-motion experiments; give a positive load inertia (kg·m²)."
        )


def _experiment_columns(exp, mode: str, i: int, yaml_path: pathlib.Path) -> dict[str, np.ndarray]:
    """The CSV columns (SI, float64, padding dropped) of unbatched experiment `i`: the required
    ones of `mode` and the measured optional ones."""
    mask = np.asarray(exp.mask, dtype=bool)
    if mask.ndim != 1:
        raise dataset_error(
            yaml_path, f"`experiments[{i}]`", "the experiment is batched", "Unstack it into single experiments."
        )

    def col(a, mask=mask):
        return np.asarray(a, dtype=np.float64)[mask]

    if mode == "friction":
        cols = {"time": col(exp.time), "velocity": col(exp.velocity), "friction_torque": col(exp.friction_torque)}
        if float(exp.has_position):
            cols["position"] = col(exp.position)
    else:
        cols = {
            "time": col(exp.time),
            "current": col(exp.current),
            "motor_velocity": col(exp.motor_velocity),
            "torque": col(exp.torque),
        }
        if mode == "free" or float(exp.has_output_position):
            cols["output_position"] = col(exp.output_position)
        if float(exp.has_motor_position):
            cols["motor_position"] = col(exp.motor_position)
    return cols


def _write_experiment_csv(path: pathlib.Path, cols: dict[str, np.ndarray], digits: int | None) -> None:
    """Write one experiment's CSV atomically, refusing NaN or inf and a time column `load_dataset`
    would refuse."""
    for k, v in cols.items():
        if not np.all(np.isfinite(v)):
            raise dataset_error(
                path,
                f"column `{k}`",
                f"refusing to write NaN or inf (sample {int(np.argmin(np.isfinite(v)))})",
                "Pass finite data.",
            )
    check_time(path, cols["time"], list(range(2, len(cols["time"]) + 2)))
    atomic_write_text(path, _csv_text(cols, digits))



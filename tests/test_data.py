"""Dataset folders (SPEC.md section 2): round trip, and one test per kind of bad input."""

import jax

jax.config.update("jax_enable_x64", True)

import re
import warnings

import numpy as np
import pytest
import yaml

from hdjax import (
    DatasetError,
    Drive,
    Experiment,
    FrictionExperiment,
    load_config,
    load_dataset,
    make_experiment,
    make_friction_experiment,
    write_dataset,
)
from hdjax._data.load import resolve_target

DRIVE = Drive(gear_ratio=160.0, torque_constant=0.1815, load_inertia=0.5)


def _grid(n=50, dt=1e-3):
    return np.arange(n) * dt


def _experiments():
    rng = np.random.default_rng(0)
    t = _grid()
    n = len(t)
    locked = make_experiment(
        t, rng.normal(size=n), rng.normal(size=n), rng.normal(size=n), mode="constrained", start_time=12.5
    )
    locked_pos = make_experiment(
        t,
        rng.normal(size=n),
        rng.normal(size=n),
        rng.normal(size=n),
        mode="constrained",
        output_position=rng.normal(size=n) * 1e-6,
        motor_position=rng.normal(size=n),
    )
    free = make_experiment(
        t + 3.0,
        rng.normal(size=n),
        rng.normal(size=n),
        rng.normal(size=n),
        mode="free",
        output_position=rng.normal(size=n),
    )
    fric = make_friction_experiment(t, np.linspace(-1, 1, n), rng.normal(size=n), position=rng.normal(size=n))
    fric_nopos = make_friction_experiment(t, np.linspace(-1, 1, n), rng.normal(size=n), start_time=300.0)
    return [locked, locked_pos, free, fric, fric_nopos]


MODES = ["constrained", "constrained", "free", "friction", "friction"]
FILES = ["locked_01.csv", "sub/locked_02.csv", "free_01.csv", "fric_01.csv", "fric_02.csv"]


def _write_csv(path, header, rows):
    lines = [",".join(header)] + [",".join(str(x) for x in r) for r in rows]
    path.write_text("\n".join(lines) + "\n")


def _good_rows(n=10, dt=0.01, ncols=4):
    return [[f"{i * dt:.6g}"] + [f"{0.1 * (i + j):.6g}" for j in range(ncols - 1)] for i in range(n)]


LOCKED_HEADER = ["time", "current", "motor_velocity", "torque"]


def _make_folder(tmp_path, csv_header=LOCKED_HEADER, rows=None, mode="constrained", yaml_text=None, file="a.csv"):
    """A one-experiment dataset folder with a hand-written CSV."""
    folder = tmp_path / "rig"
    folder.mkdir(exist_ok=True)
    _write_csv(folder / file, csv_header, _good_rows(ncols=len(csv_header)) if rows is None else rows)
    if yaml_text is None:
        yaml_text = (
            "name: test\n"
            "drive:\n  gear_ratio: 160\n  torque_constant: 0.1815\n  load_inertia: 0.5\n"
            f"experiments:\n  - file: {file}\n    mode: {mode}\n"
        )
    (folder / "dataset.yaml").write_text(yaml_text)
    return folder


# ------------------------------------------------------------------------------------------------
# Round trip
# ------------------------------------------------------------------------------------------------


def test_round_trip(tmp_path):
    exps = _experiments()
    truth = {"parameters": {"K1": np.float64(5970.0), "alpha": 1.0}, "noise": np.array([0.1, 0.2])}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_dataset(tmp_path / "ds", "bench-1", DRIVE, exps, MODES, FILES, truth=truth)
        ds = load_dataset(tmp_path / "ds")
    assert ds.name == "bench-1"
    assert ds.folder == (tmp_path / "ds").resolve()
    assert ds.files == FILES and ds.modes == MODES
    assert ds.start_times == [12.5, 0.0, 0.0, 0.0, 300.0]
    assert float(ds.drive.gear_ratio) == 160.0
    assert float(ds.drive.torque_constant) == 0.1815
    assert float(ds.drive.load_inertia) == 0.5
    assert ds.truth == {"parameters": {"K1": 5970.0, "alpha": 1.0}, "noise": [0.1, 0.2]}
    assert ds.indices("constrained") == [0, 1]
    assert ds.indices("free") == [2]
    assert ds.indices("friction") == [3, 4]
    assert ds.dynamic_indices() == [0, 1, 2]
    assert len(ds) == 5
    for a, b in zip(exps, ds.experiments):
        assert type(a) is type(b)
        for field in type(a).__dataclass_fields__:
            x, y = np.asarray(getattr(a, field)), np.asarray(getattr(b, field))
            assert x.dtype == y.dtype, field
            np.testing.assert_array_equal(x, y, err_msg=field)  # repr floats round-trip exactly
    assert isinstance(ds.experiments[0], Experiment) and isinstance(ds.experiments[3], FrictionExperiment)
    assert ds.experiments[0].time.dtype == np.float64
    # Headers as documented.
    assert (tmp_path / "ds/locked_01.csv").read_text().splitlines()[0] == "time,current,motor_velocity,torque"
    assert (tmp_path / "ds/sub/locked_02.csv").read_text().splitlines()[0] == (
        "time,current,motor_velocity,torque,output_position,motor_position"
    )
    assert (tmp_path / "ds/free_01.csv").read_text().splitlines()[0] == (
        "time,current,motor_velocity,torque,output_position"
    )
    assert (tmp_path / "ds/fric_01.csv").read_text().splitlines()[0] == "time,velocity,friction_torque,position"
    assert (tmp_path / "ds/fric_02.csv").read_text().splitlines()[0] == "time,velocity,friction_torque"
    # No temporary files left behind.
    assert not [p for p in (tmp_path / "ds").rglob("*") if p.name.endswith(".tmp")]
    # The yaml path works too, and without truth.yaml truth is None.
    (tmp_path / "ds/truth.yaml").unlink()
    ds2 = load_dataset(tmp_path / "ds" / "dataset.yaml")
    assert ds2.truth is None and ds2.files == FILES


def test_friction_only_without_drive(tmp_path):
    exps = _experiments()[3:]
    write_dataset(tmp_path / "f", "fric", None, exps, ["friction", "friction"], ["a.csv", "b.csv"])
    text = (tmp_path / "f/dataset.yaml").read_text()
    assert "drive" not in text
    ds = load_dataset(tmp_path / "f")
    assert ds.drive is None
    assert ds.dynamic_indices() == [] and ds.indices("friction") == [0, 1]
    assert float(ds.experiments[0].has_position) == 1.0 and float(ds.experiments[1].has_position) == 0.0
    assert not np.any(np.asarray(ds.experiments[1].position))


def test_hand_written_dataset_any_column_order_and_optional_columns(tmp_path):
    header = ["torque", "time", "motor_position", "current", "motor_velocity"]
    rows = [[0.5 * i, 0.01 * i, 0.2 * i, 1.0, 2.0] for i in range(5)]
    folder = _make_folder(tmp_path, header, rows)
    ds = load_dataset(folder)
    e = ds.experiments[0]
    np.testing.assert_allclose(np.asarray(e.time), 0.01 * np.arange(5))
    np.testing.assert_allclose(np.asarray(e.torque), 0.5 * np.arange(5))
    assert float(e.has_motor_position) == 1.0 and float(e.has_output_position) == 0.0
    assert float(e.free) == 0.0


def test_yaml12_floats_and_start_time(tmp_path):
    folder = _make_folder(
        tmp_path,
        yaml_text="drive:\n  gear_ratio: 1e2\n  torque_constant: 5E-2\n"
        "experiments:\n  - file: a.csv\n    mode: constrained\n    start_time: 120\n",
    )
    ds = load_dataset(folder)
    assert float(ds.drive.gear_ratio) == 100.0 and float(ds.drive.torque_constant) == 0.05
    assert ds.start_times == [120.0] and float(ds.experiments[0].start_time) == 120.0
    assert ds.name == "rig"  # folder name when absent
    assert float(ds.drive.load_inertia) == 0.0  # not needed without free experiments


def test_tiny_jitter_is_accepted(tmp_path):
    rows = _good_rows(n=20)
    rows[7][0] = f"{0.07 + 0.005 * 0.01:.10g}"  # 0.5 % of the step
    ds = load_dataset(_make_folder(tmp_path, rows=rows))
    assert ds.experiments[0].n_samples == 20


# ------------------------------------------------------------------------------------------------
# dataset.yaml errors
# ------------------------------------------------------------------------------------------------


def test_missing_dataset_yaml(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match=r"empty/dataset\.yaml.*no `dataset\.yaml`"):
        load_dataset(tmp_path / "empty")


def test_nonexistent_folder(tmp_path):
    with pytest.raises(DatasetError, match="nope.*does not exist"):
        load_dataset(tmp_path / "nope")


def test_yaml_syntax_error(tmp_path):
    folder = _make_folder(tmp_path, yaml_text="name: x\nexperiments:\n  - file: a.csv\n   mode: [constrained\n")
    with pytest.raises(DatasetError, match=r"dataset\.yaml, line \d+, column \d+: YAML syntax error"):
        load_dataset(folder)


def test_yaml_duplicate_key(tmp_path):
    folder = _make_folder(
        tmp_path, yaml_text="experiments:\n  - file: a.csv\n    mode: constrained\n    mode: free\n"
    )
    with pytest.raises(DatasetError, match=r"dataset\.yaml, line 4.*duplicate key 'mode'"):
        load_dataset(folder)


def test_top_level_not_mapping(tmp_path):
    folder = _make_folder(tmp_path, yaml_text="- file: a.csv\n  mode: constrained\n")
    with pytest.raises(DatasetError, match=r"dataset\.yaml: the top level must be a mapping"):
        load_dataset(folder)


def test_missing_experiments(tmp_path):
    folder = _make_folder(tmp_path, yaml_text="name: x\nexperiment:\n  - file: a.csv\n    mode: constrained\n")
    with pytest.warns(UserWarning, match="experiment"):
        with pytest.raises(DatasetError, match=r"dataset\.yaml, `experiments`.*did you mean `experiments`.*missing"):
            load_dataset(folder)


def test_empty_experiments(tmp_path):
    folder = _make_folder(tmp_path, yaml_text="name: x\nexperiments: []\n")
    with pytest.raises(DatasetError, match=r"dataset\.yaml, line 2 \(`experiments`\).*empty"):
        load_dataset(folder)


@pytest.mark.parametrize("key", ["file", "mode"])
def test_entry_missing_file_or_mode(tmp_path, key):
    entry = {"file": "    file: a.csv\n", "mode": "    mode: constrained\n"}
    del entry[key]
    body = "".join(entry.values()).replace("    ", "  - ", 1)
    folder = _make_folder(tmp_path, yaml_text="name: x\ndrive: {gear_ratio: 1, torque_constant: 1}\nexperiments:\n" + body)
    with pytest.raises(DatasetError, match=rf"dataset\.yaml, line 4 \(`experiments\[0\]\.{key}`\).*no `{key}`"):
        load_dataset(folder)


def test_unknown_mode(tmp_path):
    folder = _make_folder(tmp_path, mode="locked")
    with pytest.raises(
        DatasetError, match=r"dataset\.yaml, line 8 \(`experiments\[0\]\.mode`\): unknown mode 'locked'.*constrained, free, friction"
    ):
        load_dataset(folder)


def test_unknown_mode_suggests(tmp_path):
    folder = _make_folder(tmp_path, mode="constrainted")
    with pytest.raises(DatasetError, match="did you mean `constrained`"):
        load_dataset(folder)


def test_absolute_path(tmp_path):
    folder = _make_folder(tmp_path)
    text = (folder / "dataset.yaml").read_text().replace("file: a.csv", f"file: {folder / 'a.csv'}")
    (folder / "dataset.yaml").write_text(text)
    with pytest.raises(DatasetError, match=r"dataset\.yaml, line 7 \(`experiments\[0\]\.file`\).*absolute path"):
        load_dataset(folder)


def test_path_escaping_folder(tmp_path):
    folder = _make_folder(tmp_path)
    _write_csv(tmp_path / "outside.csv", LOCKED_HEADER, _good_rows())
    text = (folder / "dataset.yaml").read_text().replace("file: a.csv", "file: sub/../../outside.csv")
    (folder / "dataset.yaml").write_text(text)
    with pytest.raises(DatasetError, match=r"dataset\.yaml, line 7 \(`experiments\[0\]\.file`\).*outside\.csv.*outside the dataset folder"):
        load_dataset(folder)


def test_inner_dotdot_is_fine(tmp_path):
    folder = _make_folder(tmp_path)
    (folder / "sub").mkdir()
    text = (folder / "dataset.yaml").read_text().replace("file: a.csv", "file: sub/../a.csv")
    (folder / "dataset.yaml").write_text(text)
    assert load_dataset(folder).files == ["sub/../a.csv"]


def test_file_missing(tmp_path):
    folder = _make_folder(tmp_path)
    (folder / "a.csv").unlink()
    with pytest.raises(DatasetError, match=r"rig/a\.csv, named in .*dataset\.yaml line 7.*does not exist"):
        load_dataset(folder)


def test_duplicate_files(tmp_path):
    folder = _make_folder(tmp_path)
    text = (folder / "dataset.yaml").read_text() + "  - file: ./a.csv\n    mode: free\n"
    (folder / "dataset.yaml").write_text(text)
    with pytest.raises(DatasetError, match=r"dataset\.yaml, line 9 \(`experiments\[1\]\.file`\).*`\./a\.csv` is listed twice"):
        load_dataset(folder)


def test_missing_drive_block(tmp_path):
    folder = _make_folder(tmp_path, yaml_text="experiments:\n  - file: a.csv\n    mode: constrained\n")
    with pytest.raises(DatasetError, match=r"dataset\.yaml, `drive`: the `drive` block is missing.*constrained"):
        load_dataset(folder)


def test_missing_gear_ratio(tmp_path):
    folder = _make_folder(
        tmp_path,
        yaml_text="drive:\n  gear_ration: 160\n  torque_constant: 0.18\n"
        "experiments:\n  - file: a.csv\n    mode: constrained\n",
    )
    with pytest.warns(UserWarning, match="gear_ration") as record:
        with pytest.raises(
            DatasetError, match=r"dataset\.yaml, line 1 \(`drive`\): `drive\.gear_ratio`.*missing.*gear_ration"
        ):
            load_dataset(folder)
    assert record[0].filename == __file__  # the warning points at the caller of load_dataset


@pytest.mark.parametrize("value", ["0", "-0.18", "abc", ".nan"])
def test_bad_torque_constant(tmp_path, value):
    folder = _make_folder(
        tmp_path,
        yaml_text=f"drive:\n  gear_ratio: 160\n  torque_constant: {value}\n"
        "experiments:\n  - file: a.csv\n    mode: constrained\n",
    )
    with pytest.raises(DatasetError, match=r"dataset\.yaml, line 3 \(`drive\.torque_constant`\).*not a positive"):
        load_dataset(folder)


def test_missing_load_inertia_with_free(tmp_path):
    header = LOCKED_HEADER + ["output_position"]
    folder = _make_folder(
        tmp_path,
        header,
        mode="free",
        yaml_text="drive:\n  gear_ratio: 160\n  torque_constant: 0.18\nexperiments:\n  - file: a.csv\n    mode: free\n",
    )
    with pytest.raises(DatasetError, match=r"dataset\.yaml, line 1 \(`drive`\): `drive\.load_inertia`.*missing.*free"):
        load_dataset(folder)


def test_nonpositive_load_inertia_with_free(tmp_path):
    header = LOCKED_HEADER + ["output_position"]
    folder = _make_folder(
        tmp_path,
        header,
        mode="free",
        yaml_text="drive:\n  gear_ratio: 160\n  torque_constant: 0.18\n  load_inertia: 0\n"
        "experiments:\n  - file: a.csv\n    mode: free\n",
    )
    with pytest.raises(DatasetError, match=r"dataset\.yaml, line 4 \(`drive\.load_inertia`\).*not a positive"):
        load_dataset(folder)


@pytest.mark.parametrize("value", ["soon", "true", "-5"])
def test_bad_start_time(tmp_path, value):
    folder = _make_folder(tmp_path)
    text = (folder / "dataset.yaml").read_text() + f"    start_time: {value}\n"
    (folder / "dataset.yaml").write_text(text)
    with pytest.raises(DatasetError, match=r"dataset\.yaml, line 9 \(`experiments\[0\]\.start_time`\).*not a finite"):
        load_dataset(folder)


# ------------------------------------------------------------------------------------------------
# CSV errors
# ------------------------------------------------------------------------------------------------


def test_csv_no_header(tmp_path):
    folder = _make_folder(tmp_path)
    _write_csv(folder / "a.csv", ["0", "1", "2", "3"], _good_rows())
    with pytest.raises(DatasetError, match=r"a\.csv, line 1: there is no header row"):
        load_dataset(folder)


def test_csv_missing_column_did_you_mean(tmp_path):
    folder = _make_folder(tmp_path, ["time", "current", "motor_velocty", "torque"])
    with pytest.raises(
        DatasetError, match=r"a\.csv, line 1 \(header\): .*`motor_velocity`.*found `motor_velocty`: did you mean"
    ):
        load_dataset(folder)


def test_csv_missing_column_no_suggestion(tmp_path):
    folder = _make_folder(tmp_path, ["time", "current", "torque"])
    with pytest.raises(DatasetError, match=r"a\.csv, line 1 \(header\): constrained experiments need column\(s\) `motor_velocity`") as e:
        load_dataset(folder)
    assert "did you mean" not in str(e.value)


def test_csv_free_needs_output_position(tmp_path):
    folder = _make_folder(tmp_path, mode="free")
    with pytest.raises(DatasetError, match=r"a\.csv, line 1 \(header\): free experiments need column\(s\) `output_position`"):
        load_dataset(folder)


def test_csv_friction_columns(tmp_path):
    folder = _make_folder(tmp_path, ["time", "velocity", "torque"], mode="friction")
    with pytest.raises(DatasetError, match=r"a\.csv, line 1 \(header\): friction experiments need .*`friction_torque`"):
        load_dataset(folder)


def test_csv_duplicate_columns(tmp_path):
    folder = _make_folder(tmp_path, ["time", "current", "motor_velocity", "torque", "torque"])
    with pytest.raises(DatasetError, match=r"a\.csv, line 1, column\(s\) `torque`: duplicate column"):
        load_dataset(folder)


def test_csv_non_numeric_cell(tmp_path):
    rows = _good_rows()
    rows[4][2] = "fast"  # motor_velocity on file line 6 (header is line 1)
    folder = _make_folder(tmp_path, rows=rows)
    with pytest.raises(DatasetError, match=r"a\.csv, line 6, column `motor_velocity`: non-numeric value 'fast'"):
        load_dataset(folder)


def test_csv_empty_cell(tmp_path):
    rows = _good_rows()
    rows[2][1] = ""
    folder = _make_folder(tmp_path, rows=rows)
    with pytest.raises(DatasetError, match=r"a\.csv, line 4, column `current`: empty cell"):
        load_dataset(folder)


def test_csv_wrong_field_count(tmp_path):
    rows = _good_rows()
    rows[3].append("7")
    folder = _make_folder(tmp_path, rows=rows)
    with pytest.raises(DatasetError, match=r"a\.csv, line 5: the row has 5 field"):
        load_dataset(folder)


@pytest.mark.parametrize(("value", "word"), [("nan", "NaN"), ("NaN", "NaN"), ("inf", "inf"), ("-Infinity", "inf")])
def test_csv_nan_inf(tmp_path, value, word):
    rows = _good_rows()
    rows[6][3] = value
    folder = _make_folder(tmp_path, rows=rows)
    with pytest.raises(DatasetError, match=rf"a\.csv, line 8, column `torque`: value '{value}' is {word}"):
        load_dataset(folder)


def test_csv_too_few_rows(tmp_path):
    folder = _make_folder(tmp_path, rows=_good_rows(n=2))
    with pytest.raises(DatasetError, match=r"a\.csv, column `time`: only 2 data row"):
        load_dataset(folder)


def test_csv_time_not_increasing(tmp_path):
    rows = _good_rows()
    rows[5][0], rows[6][0] = rows[6][0], rows[5][0]
    folder = _make_folder(tmp_path, rows=rows)
    with pytest.raises(DatasetError, match=r"a\.csv, line 8, column `time`: time is not strictly increasing"):
        load_dataset(folder)


def test_csv_time_error_prints_plain_numbers(tmp_path):
    """The message shows the times as the CSV has them (`0.06 s`), not `np.float64(0.06) s`."""
    rows = _good_rows()
    rows[5][0], rows[6][0] = rows[6][0], rows[5][0]
    folder = _make_folder(tmp_path, rows=rows)
    with pytest.raises(DatasetError) as info:
        load_dataset(folder)
    msg = str(info.value)
    assert "np.float64" not in msg and "float64" not in msg
    assert "(0.06 s on line 7, then 0.05 s)" in msg


def test_csv_uneven_time_prints_plain_numbers(tmp_path):
    rows = [[f"{t:.6g}", 1, 2, 3] for t in [0.0, 0.01, 0.02, 0.03, 0.05, 0.06, 0.07, 0.08]]
    folder = _make_folder(tmp_path, rows=rows)
    with pytest.raises(DatasetError) as info:
        load_dataset(folder)
    assert "np.float64" not in str(info.value) and "uneven time step: 0.02" in str(info.value)


def test_csv_repeated_time(tmp_path):
    rows = _good_rows()
    rows[3][0] = rows[2][0]
    folder = _make_folder(tmp_path, rows=rows)
    with pytest.raises(DatasetError, match=r"a\.csv, line 5, column `time`: time is not strictly increasing"):
        load_dataset(folder)


def test_csv_uneven_time(tmp_path):
    rows = [[f"{t:.6g}", 1, 2, 3] for t in [0.0, 0.01, 0.02, 0.03, 0.05, 0.06, 0.07, 0.08]]  # gap after 0.03
    folder = _make_folder(tmp_path, rows=rows)
    with pytest.raises(DatasetError, match=r"a\.csv, line 6, column `time`: uneven time step.*never resamples"):
        load_dataset(folder)


def test_csv_jitter_just_above_one_percent(tmp_path):
    rows = _good_rows(n=20)
    rows[10][0] = f"{0.10 + 0.012 * 0.01:.10g}"  # 1.2 % of the step
    folder = _make_folder(tmp_path, rows=rows)
    with pytest.raises(DatasetError, match=r"a\.csv, line 12, column `time`: uneven time step"):
        load_dataset(folder)


def test_csv_extra_columns_warn_once(tmp_path):
    header = ["time", "current", "temperature", "motor_velocity", "torque", "comment"]
    rows = [[0.01 * i, 1.0, 25.0, 2.0, 3.0, "ok"] for i in range(5)]
    folder = _make_folder(tmp_path, header, rows)
    with pytest.warns(UserWarning) as record:
        ds = load_dataset(folder)
    assert len(record) == 1
    msg = str(record[0].message)
    assert "a.csv" in msg and "`temperature`" in msg and "`comment`" in msg
    assert record[0].filename == __file__  # the caller of load_dataset
    np.testing.assert_allclose(np.asarray(ds.experiments[0].torque), 3.0)  # the text column is never parsed


def test_csv_semicolon_hint(tmp_path):
    folder = _make_folder(tmp_path)
    (folder / "a.csv").write_text("time;current;motor_velocity;torque\n0;1;2;3\n")
    with pytest.raises(DatasetError, match=r"a\.csv.*delimiter other than a comma"):
        load_dataset(folder)


def test_csv_empty(tmp_path):
    folder = _make_folder(tmp_path)
    (folder / "a.csv").write_text("")
    with pytest.raises(DatasetError, match=r"a\.csv: the CSV is empty"):
        load_dataset(folder)


def test_error_message_is_one_paragraph(tmp_path):
    folder = _make_folder(tmp_path, mode="locked")
    with pytest.raises(DatasetError) as e:
        load_dataset(folder)
    assert "\n" not in str(e.value)
    assert isinstance(e.value, ValueError)


# ------------------------------------------------------------------------------------------------
# Configs and targets
# ------------------------------------------------------------------------------------------------


def _config(tmp_path, text):
    (tmp_path / "configs").mkdir(exist_ok=True)
    p = tmp_path / "configs" / "hd.yaml"
    p.write_text(text)
    return p


def test_load_config_and_resolve_target(tmp_path):
    folder = _make_folder(tmp_path)
    cfg = _config(tmp_path, "dataset: ../rig\nfit:\n  max_steps: 20\n")
    config = load_config(cfg)
    assert config["dataset"] == folder.resolve() and config["dataset"].is_absolute()
    assert config["fit"] == {"max_steps": 20} and type(config["fit"]) is dict

    ds, config2 = resolve_target(cfg)
    assert ds.folder == folder.resolve() and config2["fit"]["max_steps"] == 20
    ds, config3 = resolve_target(folder)
    assert config3 == {} and ds.files == ["a.csv"]
    ds, config4 = resolve_target(folder / "dataset.yaml")
    assert config4 == {} and ds.modes == ["constrained"]


def test_config_errors(tmp_path):
    with pytest.raises(DatasetError, match="missing.yaml.*does not exist"):
        load_config(tmp_path / "missing.yaml")
    with pytest.raises(DatasetError, match=r"hd\.yaml, `dataset`.*did you mean `dataset`.*no `dataset` key"):
        load_config(_config(tmp_path, "datset: ../rig\n"))
    with pytest.raises(DatasetError, match=r"hd\.yaml, line 2, column \d+: YAML syntax error"):
        load_config(_config(tmp_path, "dataset: ../rig\n  fit: : [\n"))
    with pytest.raises(DatasetError, match=r"hd\.yaml, line 1 \(`dataset`\): the dataset folder .*nowhere does not exist"):
        resolve_target(_config(tmp_path, "dataset: ../nowhere\n"))
    with pytest.raises(DatasetError, match="nothing-here.*does not exist"):
        resolve_target(tmp_path / "nothing-here")
    (tmp_path / "x.txt").write_text("hi")
    with pytest.raises(DatasetError, match=r"x\.txt.*neither a folder nor a \.yaml"):
        resolve_target(tmp_path / "x.txt")


# ------------------------------------------------------------------------------------------------
# write_dataset refusals and atomicity
# ------------------------------------------------------------------------------------------------


def test_write_dataset_refuses_bad_input(tmp_path):
    exps = _experiments()
    with pytest.raises(DatasetError, match="drive"):
        write_dataset(tmp_path / "w", "x", None, exps[:1], ["constrained"], ["a.csv"])
    with pytest.raises(DatasetError, match="load_inertia"):
        write_dataset(tmp_path / "w", "x", Drive(160.0, 0.18, 0.0), exps[2:3], ["free"], ["a.csv"])
    with pytest.raises(DatasetError, match="disagrees"):
        write_dataset(tmp_path / "w", "x", DRIVE, exps[:1], ["free"], ["a.csv"])
    with pytest.raises(DatasetError, match="outside the dataset folder"):
        write_dataset(tmp_path / "w", "x", DRIVE, exps[:1], ["constrained"], ["../a.csv"])
    with pytest.raises(DatasetError, match="twice"):
        write_dataset(tmp_path / "w", "x", DRIVE, exps[:2], MODES[:2], ["a.csv", "a.csv"])
    assert not (tmp_path / "w" / "dataset.yaml").exists()


def test_write_dataset_overwrites_and_explicit_start_times(tmp_path):
    exps = _experiments()[:1]
    write_dataset(tmp_path / "w", "one", DRIVE, exps, ["constrained"], ["a.csv"])
    write_dataset(tmp_path / "w", "two", DRIVE, exps, ["constrained"], ["a.csv"], start_times=[7.0])
    doc = yaml.safe_load((tmp_path / "w/dataset.yaml").read_text())
    assert doc["name"] == "two" and doc["experiments"][0]["start_time"] == 7.0
    ds = load_dataset(tmp_path / "w")
    assert ds.start_times == [7.0] and float(ds.experiments[0].start_time) == 7.0
    assert sorted(p.name for p in (tmp_path / "w").iterdir()) == ["a.csv", "dataset.yaml"]
    assert re.fullmatch(r"[-+0-9.e,]+", (tmp_path / "w/a.csv").read_text().splitlines()[1])


def test_dynamic_part_names_the_command_the_folder_and_the_fix(tmp_path):
    """Every command that simulates takes its experiments through `Dataset.dynamic_part`; a
    dataset without them gets one clear error (friction-only data: where they do go instead)."""
    from hdjax import Dataset
    from helpers import hd2, sine_experiment

    t = np.arange(200) * 1e-3
    fric = make_friction_experiment(t, np.linspace(-1, 1, t.size), np.zeros(t.size))
    only_friction = Dataset("f", tmp_path, None, [fric], ["f.csv"], ["friction"], [0.0])
    with pytest.raises(DatasetError, match=r"dataset\.yaml: `tune` needs at least 1 constrained or free experiment "
                                           r"and a `drive` block; this dataset has 1 friction experiments and no "
                                           r"`drive` block\..*fitted and diagnosed as friction"):
        only_friction.dynamic_part("tune")
    _, drive = hd2()
    one = Dataset("d", tmp_path, drive, [sine_experiment("free"), fric], ["a.csv", "f.csv"], ["free", "friction"],
                  [0.0, 0.0])
    part = one.dynamic_part("fit")
    assert part.drive is drive and part.files == ["a.csv"] and part.modes == ["free"] and len(part.experiments) == 1
    with pytest.raises(DatasetError, match=r"`diagnose` needs at least 2 constrained or free experiments"):
        one.dynamic_part("diagnose", at_least=2)

"""Commands refuse bad input with a clear message and a non-zero exit status."""

import subprocess
import sys


def _run(*args):
    return subprocess.run([sys.executable, "-m", "hdjax.fit", *args], capture_output=True, text=True, timeout=120)


def test_fit_missing_target_fails_with_message(tmp_path):
    r = _run(str(tmp_path / "nope"), "--out", str(tmp_path / "out"))
    assert r.returncode != 0
    assert "nope" in r.stderr
    assert not (tmp_path / "out" / "fit.json").exists()


def test_fit_bad_dataset_names_file_and_field(tmp_path):
    (tmp_path / "dataset.yaml").write_text("name: x\nexperiments:\n  - file: a.csv\n    mode: sideways\n")
    (tmp_path / "a.csv").write_text("time,current\n0,0\n")
    r = _run(str(tmp_path), "--out", str(tmp_path / "out"))
    assert r.returncode == 2
    assert "dataset.yaml" in r.stderr and "mode" in r.stderr

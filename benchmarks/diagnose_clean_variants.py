"""Benchmark (not a test): does `hdjax diagnose` name nothing on clean data when the session is
laid out differently from the 20-dataset benchmark (`diagnose_independent.py`: 8 locked + 8 free
records of 2.5 s at 1 kHz)?

Eight clean datasets from the independent bench (`hdjax.bench.make_dataset`, every deviation on, no
effect hidden), six of them changing one thing a user's bench may change: the sampling rate (500 Hz,
2 kHz), the record length (6 + 6 records of 5 s), the mix of tests (12 locked + 4 free), the
low-speed law (LuGre) and the noise (scaled with each record's range); two change the last two at
once (at 1 kHz and at 500 Hz). The seeds (6001–6008) are
used by no test and no other benchmark. Each dataset is diagnosed by the command a user runs,
`python -m hdjax.diagnose DIR --out DIR/result --quiet`, one after the other. Prints, per
dataset, the findings (there should be none), the model_form items adopted and the time.

Usage: `python benchmarks/diagnose_clean_variants.py [--only c6004_12l4f,...] [--workdir DIR]`.
"""

import argparse
import json
import pathlib
import subprocess
import sys
import tempfile
import time

VARIANTS = {
    "c6001_500hz": dict(drive="hd2", seed=6001, sample_rate=500.0),
    "c6002_2khz": dict(drive="hd1", seed=6002, sample_rate=2000.0, duration=2.0),
    "c6003_5s": dict(drive="hd2", seed=6003, n_locked=6, n_free=6, duration=5.0),
    "c6004_12l4f": dict(drive="hd1", seed=6004, n_locked=12, n_free=4),
    "c6005_lugre": dict(drive="hd2", seed=6005, low_speed="lugre"),
    "c6006_perrec": dict(drive="hd1", seed=6006, noise="per_record"),
    # both variant switches at once (twenty-ninth session)
    "c6007_lugre_perrec": dict(drive="hd2", seed=6007, low_speed="lugre", noise="per_record"),
    "c6008_lugre_perrec_500hz": dict(drive="hd1", seed=6008, sample_rate=500.0, low_speed="lugre", noise="per_record"),
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=None, help="comma-separated names of VARIANTS")
    ap.add_argument("--workdir", default=None, help="keep datasets and results here (default: a temporary folder)")
    args = ap.parse_args(argv)
    names = args.only.split(",") if args.only else list(VARIANTS)
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        ap.error(f"unknown variant(s) {unknown}; choose from {list(VARIANTS)}")
    from hdjax.bench import make_dataset

    work = pathlib.Path(args.workdir) if args.workdir else pathlib.Path(tempfile.mkdtemp(prefix="hdjax-clean-"))
    rows = []
    for name in names:
        folder = work / name
        if not (folder / "dataset.yaml").exists():
            make_dataset(folder, **VARIANTS[name])
        t0 = time.perf_counter()
        run = subprocess.run([sys.executable, "-m", "hdjax.diagnose", str(folder), "--out", str(folder / "result"), "--quiet"],
                             capture_output=True, text=True)
        dt = time.perf_counter() - t0
        if run.returncode != 0:
            print(f"{name}: hdjax diagnose failed (exit {run.returncode}):\n{run.stderr[-2000:]}", flush=True)
            rows.append({"variant": name, "findings": None, "time_s": round(dt, 1)})
            continue
        d = json.loads((folder / "result" / "diagnosis.json").read_text())
        row = {"variant": name, "findings": [[f["effect"], f.get("orders")] for f in d["findings"]],
               "model_form": [m["assumption"] for m in d["model_form"]], "time_s": round(dt, 1)}
        rows.append(row)
        print(json.dumps(row), flush=True)
    clean = sum(1 for r in rows if r["findings"] == [])
    times = ", ".join(f"{r['time_s']:.0f}" for r in rows)
    print(f"\n{clean} / {len(rows)} clean variants with no finding; times {times} s")
    return 0 if clean == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())

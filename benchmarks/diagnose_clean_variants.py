"""Benchmark (not a test): does `hdjax diagnose` name nothing on clean data when the session is
laid out differently from the 20-dataset benchmark (`diagnose_independent.py`: 8 locked + 8 free
records of 2.5 s at 1 kHz)?

Thirteen clean datasets from the independent bench (`hdjax.bench.make_dataset`, every deviation on, no
effect hidden), six of them changing one thing a user's bench may change: the sampling rate (500 Hz,
2 kHz), the record length (6 + 6 records of 5 s), the mix of tests (12 locked + 4 free), the
low-speed law (LuGre) and the noise (scaled with each record's range); two change the last two at
once (at 1 kHz and at 500 Hz); five change the sensors (`Deviations`): a tachometer ripple at order 1
or 2 of the wave generator, a 12-bit output encoder, slow sensor filters, a slow current loop. The
seeds (6001–6008, 7001–7005) are used by no test and no other benchmark. Each dataset is diagnosed by the command a user runs,
`python -m hdjax.diagnose DIR --out DIR/result --quiet`, one after the other. Prints, per
dataset, the findings (there should be none), the model_form items adopted and the time.

Usage: `python benchmarks/diagnose_clean_variants.py [--only c6004_12l4f,...] [--workdir DIR]
[--negligible-record-loss 0]`.
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
    # sensors unlike the default bench's (forty-second session; `deviations`: fields of `hdjax.bench.Deviations`):
    # a tachometer ripple at a low order of the wave generator, where the periodic effects sit (the bench's
    # default is order 11), as large as the tachometer noise; a 12-bit output encoder; slow strain gauge and
    # tachometer filters; a slow current loop with three times the PWM ripple
    "c7001_tacho_ripple_o2": dict(drive="hd2", seed=7001, deviations=dict(tacho_ripple=1.0, tacho_ripple_order=2)),
    "c7002_tacho_ripple_o1": dict(drive="hd1", seed=7002, deviations=dict(tacho_ripple=1.0, tacho_ripple_order=1)),
    "c7003_coarse_encoder": dict(drive="hd2", seed=7003, deviations=dict(encoder_counts=2**12)),
    "c7004_slow_sensors": dict(drive="hd1", seed=7004, deviations=dict(torque_filter=(120.0, 180.0), tacho_filter=(80.0, 120.0))),
    "c7005_weak_current_loop": dict(drive="hd2", seed=7005, deviations=dict(current_bandwidth=500.0, pwm_ripple=1.5)),
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=None, help="comma-separated names of VARIANTS")
    ap.add_argument("--workdir", default=None, help="keep datasets and results here (default: a temporary folder)")
    ap.add_argument("--negligible-record-loss", type=float, default=None,
                    help="run the command with this `diagnose: negligible_record_loss` (a config file beside the "
                         "dataset; default: the command's own default)")
    ap.add_argument("--measured-angle", default=None, choices=("on", "off"),
                    help="run the command with this `diagnose: measured_angle` (a config file beside the dataset; "
                         "default: the command's own default)")
    args = ap.parse_args(argv)
    names = args.only.split(",") if args.only else list(VARIANTS)
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        ap.error(f"unknown variant(s) {unknown}; choose from {list(VARIANTS)}")
    from hdjax.bench import Deviations, make_dataset

    work = pathlib.Path(args.workdir) if args.workdir else pathlib.Path(tempfile.mkdtemp(prefix="hdjax-clean-"))
    rows = []
    for name in names:
        folder = work / name
        if not (folder / "dataset.yaml").exists():
            kwargs = dict(VARIANTS[name])
            if "deviations" in kwargs:
                kwargs["deviations"] = Deviations(**kwargs["deviations"])
            make_dataset(folder, **kwargs)
        target = str(folder)
        options = {}
        if args.negligible_record_loss is not None:
            options["negligible_record_loss"] = repr(args.negligible_record_loss)
        if args.measured_angle is not None:
            options["measured_angle"] = "true" if args.measured_angle == "on" else "false"
        if options:
            target = str(folder / "options.yaml")
            pathlib.Path(target).write_text("dataset: .\ndiagnose:\n" + "".join(f"  {k}: {v}\n" for k, v in options.items()))
        t0 = time.perf_counter()
        run = subprocess.run([sys.executable, "-m", "hdjax.diagnose", target, "--out", str(folder / "result"), "--quiet"],
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

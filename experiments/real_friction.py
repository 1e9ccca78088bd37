"""Eq. 9 and the friction diagnosis on a real friction-only dataset folder.

    python experiments/real_friction.py ../shared/real-data/franka-joint2 [--out DIR] [--per-record]

Prints, per record: eq. 9 and its special case, symmetric Coulomb + viscous (linear least squares),
each fitted on the record alone, RMS error raw and low-passed at 1 Hz (`hdjax.filtered_rms`,
the published comparisons' metric), both over the whole file (fitted on all of it, as the published
table) and held out (fitted on the first 70 %, scored on the last 30 %); against the published
baselines found in the folder's SOURCE.md (lines like `case3 slow: Coulomb+viscous 0.206, ...`);
then the cross-validated diagnosis of the whole dataset
(and, with --per-record, of each record alone by contiguous time blocks), what it names and the held-out gain. Writes
figures into DIR (default results/real-<folder name>). Never copies the data.
"""

import argparse
import pathlib
import re
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

from hdjax import FrictionProblem, fit_coulomb_viscous, friction_diagnosis_doc, load_dataset, rms_stats  # noqa: E402
from hdjax.plotting import friction_cv_figure, friction_heldout_time_figure, friction_velocity_figure  # noqa: E402


def published(folder: pathlib.Path) -> dict[str, dict[str, float]]:
    """`{record key: {model: RMS}}` from SOURCE.md lines `key: model value, model value, ...`."""
    src = folder / "SOURCE.md"
    out = {}
    if not src.exists():
        return out
    for line in src.read_text().splitlines():
        m = re.match(r"^\s*([\w .\-]+?):\s*(.+)$", line)
        if not m:
            continue
        vals = dict((k.strip(), float(v)) for k, v in re.findall(r"([A-Za-z][\w+ ()\-]*?)\s+(\d+\.\d+)", m.group(2)))
        if vals:
            out[m.group(1).strip()] = vals
    return out


def _match(file: str, table: dict) -> dict | None:
    stem = re.sub(r"[_\-]", " ", pathlib.Path(file).stem).lower()
    for k, v in table.items():
        if re.sub(r"[_\-]", " ", k).lower() == stem:
            return v
    return None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folder")
    ap.add_argument("--out", default=None)
    ap.add_argument("--per-record", action="store_true",
                    help="also diagnose each record alone (contiguous time blocks); slower, and a single "
                         "constant-speed record cannot determine eq. 9, so read those findings with care")
    args = ap.parse_args()
    folder = pathlib.Path(args.folder)
    out = pathlib.Path(args.out or f"results/real-{folder.resolve().name}")
    t_all = time.time()
    ds = load_dataset(folder)
    if not all(m == "friction" for m in ds.modes):
        print(f"{folder}: not a friction-only dataset ({sorted(set(ds.modes))})", file=sys.stderr)
        return 2
    table = published(folder)
    problem = FrictionProblem(list(ds.experiments), list(ds.files))

    print(f"# {ds.name}: {problem.E} records, {int(problem.mask.sum())} samples")
    npos, nneg = problem.directions(problem.mask.astype(float))
    print(f"velocity samples beyond {3 * problem.smoothing.velocity_scale:g} rad/s: {npos} positive, {nneg} negative")

    t0 = time.time()
    rec = problem.rows_records(0.7)
    fit = problem.fit_eq9(rec)
    full = problem.rows_full()
    fitf = problem.fit_eq9(full)
    t_eq9 = time.time() - t0
    print(f"\n## each record fitted alone: eq. 9 and its special case Coulomb + viscous ({t_eq9:.1f} s)")
    print("RMS error (N·m) raw and low-passed at 1 Hz (zero-phase 4th-order Butterworth, MATLAB filtfilt padding) "
          "= the published metric. 'whole file': fitted on every sample, RMS over the whole file (in-sample, as "
          "the published table); 'held-out': fitted on the first 70 %, RMS over the last 30 % (that span filtered "
          "on its own).\n")
    print("| record | model | whole file raw | whole file 1 Hz | held-out raw | held-out 1 Hz | published (N·m, 1 Hz, whole file) |")
    print("|---|---|---|---|---|---|---|")
    fs = problem.fs
    for e, f in enumerate(ds.files):
        w_all, tr, te = full.train[1 + e], rec.train[1 + e], rec.test[1 + e]
        _, _, cv_all = fit_coulomb_viscous(problem, w_all)
        _, _, cv_tr = fit_coulomb_viscous(problem, tr)
        pub = _match(f, table)
        pub_s = ", ".join(f"{k} {v:g}" for k, v in pub.items()) if pub else "none in SOURCE.md"
        for name, pa, ph in (("eq. 9", fitf.prediction[1 + e], fit.prediction[1 + e]),
                             ("Coulomb + viscous (symmetric LS)", cv_all, cv_tr)):
            a = rms_stats(pa, problem.T, w_all, fs=fs)
            h = rms_stats(ph, problem.T, te, fs=fs)
            print(f"| {f} | {name} | {a['rms']:.4g} | {a['rms_lowpass_1hz']:.4g} | {h['rms']:.4g} | "
                  f"{h['rms_lowpass_1hz']:.4g} | {pub_s if name == 'eq. 9' else ''} |")
    pooled = rms_stats(fit.prediction[0], problem.T, rec.test[0], fs=fs)
    _, _, cvp = fit_coulomb_viscous(problem, rec.train[0])
    cvs = rms_stats(cvp, problem.T, rec.test[0], fs=fs)
    print(f"pooled fit (all records' first 70 %): held-out RMS eq. 9 {pooled['rms']:.4g} N·m "
          f"(1 Hz {pooled['rms_lowpass_1hz']:.4g}), NRMSE {pooled['nrmse']:.3f}; Coulomb + viscous {cvs['rms']:.4g} N·m "
          f"(1 Hz {cvs['rms_lowpass_1hz']:.4g})")
    friction_heldout_time_figure(problem, fit, rec, out / "eq9_heldout_time.png")
    friction_velocity_figure(problem, fit.prediction[0], out / "eq9_vs_velocity.png", "eq. 9, pooled fit on first 70 %")

    print("\n## diagnosis of the whole dataset (cross-validated)")
    t0 = time.time()
    doc = friction_diagnosis_doc(problem, ds.name, log=print)
    friction_cv_figure(problem, doc["_d"], out / "diagnosis_dataset.png")
    _report(doc, time.time() - t0)

    if args.per_record and problem.E > 1:
        for e, f in enumerate(ds.files):
            if problem.E > 3 and e not in (0, problem.E - 1):
                continue  # many short records: the first and last only, to bound the run time
            print(f"\n## diagnosis of {f} alone (contiguous time blocks)")
            t0 = time.time()
            pe = FrictionProblem([ds.experiments[e]], [f])
            try:
                d = friction_diagnosis_doc(pe, f"{ds.name}/{f}", log=print)
            except ValueError as err:
                print(f"not diagnosable: {err}")
                continue
            friction_cv_figure(pe, d["_d"], out / f"diagnosis_{pathlib.Path(f).stem}.png")
            _report(d, time.time() - t0)
    print(f"\ntotal {time.time() - t_all:.1f} s; figures in {out}")
    return 0


def _report(doc, dt):
    b = doc["baseline"]
    print(f"eq. 9 cross-validated held-out RMS {b['heldout_rms']:.4g} N·m, 1 Hz low-passed "
          f"{b['heldout_rms_lowpass_1hz']:.4g} N·m (NRMSE {b['heldout_nrmse']['friction_torque']:.3f})")
    x = doc["extended_model"]
    if doc["findings"]:
        print(f"extended model cross-validated held-out RMS {x['heldout_rms']:.4g} N·m, 1 Hz low-passed "
              f"{x['heldout_rms_lowpass_1hz']:.4g} N·m")
    if not doc["findings"]:
        print("findings: none significant")
    for f in doc["findings"]:
        g = f["gain"]
        print(f"finding: {f['effect']} {f.get('orders', '')} held-out RMS {g['heldout_rms_before']:.4g} → "
              f"{g['heldout_rms_after']:.4g} N·m ({g['relative_reduction']:+.1%}); parameters "
              + ", ".join(f"{k}={v:.3g}" for k, v in f["parameters"].items()))
    for u in doc["unexplained"]:
        print(f"unexplained: {u['description']}: {u['evidence']}")
    print(f"({dt:.1f} s)")


if __name__ == "__main__":
    sys.exit(main())

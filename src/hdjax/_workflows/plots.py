"""Every figure the commands write, and the only module that imports matplotlib (Agg backend).

One function per workflow (`fit_figures`, `sensitivity_figures`, `tune_figures`,
`diagnosis_figures`, and the friction-only figures), each taking the workflow's computed results
and an output folder and writing PNGs atomically (`hdjax._workflows.io.atomic_savefig`). The workflows import
this module when they draw, so a library import never loads matplotlib."""

import pathlib

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.colors import LogNorm  # noqa: E402

from .._data.experiment import CHANNEL_UNITS, stack_experiments
from .._discrepancy.evidence import TB_MAX_RATIO, TB_MEDIAN_RATIO
from .._fit.least_squares import CHANNELS
from .._fit.sensitivity import ABLATIONS, CHANNEL_SYMBOL
from .._model.effects import MAX_ORDER
from .._model.paper import Parameters
from .fit import hysteresis_curves
from .io import atomic_savefig
from .tune import CONTROLLERS, LABELS


def _save(fig, out: pathlib.Path, name: str, names: list[str], **savefig) -> None:
    """Write `fig` atomically to `out / name`, close it and record `name` in `names`."""
    atomic_savefig(fig, out / name, **savefig)
    plt.close(fig)
    names.append(name)


COLORS = {"relay_zn": "tab:orange", "model_pi": "tab:purple", "tuned": "tab:blue"}


# ---- fit ----

def fit_figures(out, p: Parameters, paper, full, traj, modes, files, drive, experiments) -> list[str]:
    """Paper-style figures of `hdjax fit` into folder `out`: Fig. 3 (hysteresis torsion curve of the
    largest locked test with the paper's two compliance regressions), Fig. 4 (torque, measured vs
    simulated, four typical tests) and Fig. 5 (velocity and torque, one free and one locked test).
    Returns the file names written."""
    m = np.asarray(full.mask)
    t = np.asarray(full.time)
    cons = [j for j, md in enumerate(modes) if md == "constrained"]
    free = [j for j, md in enumerate(modes) if md == "free"]
    names = []

    # Fig. 3: hysteresis torsion curve of the locked record with the largest torque, with the
    # paper's two compliance regressions of that record (each its own least-squares fit)
    if cons:
        j = max(cons, key=lambda j: float(np.max(np.abs(np.asarray(full.torque)[j][m[j]]))))
        loop = hysteresis_curves(paper, experiments[j], drive, j)
        fig, ax = plt.subplots(figsize=(6, 4.5))
        ax.plot(loop["torsion"] * 1e3, loop["torque"], ".", ms=2, color="0.6", label="measured")
        for c, style in zip(loop["curves"], ("--", "-.")):
            ax.plot(loop["torsion"] * 1e3, c["torque"], style, label=f"{c['label']} (RMS error {c['rms']:.3g} N·m)")
        ax.set_xlabel("torsion Δθ = θm/N (mrad)")
        ax.set_ylabel("torque T (N·m)")
        ax.set_title(f"Hysteresis torsion curve ({files[j]})")
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
        _save(fig, out, "fig3_hysteresis.png", names, dpi=120, bbox_inches="tight")

    # Fig. 4: torque fit on four typical experiments
    pick = (cons[:2] + free[:2]) if len(cons) >= 2 and len(free) >= 2 else (cons + free)[:4]
    if pick:
        fig, axes = plt.subplots(len(pick), 1, figsize=(8, 2.2 * len(pick)), squeeze=False)
        for ax, j in zip(axes[:, 0], pick):
            ax.plot(t[j][m[j]], np.asarray(full.torque)[j][m[j]], color="0.6", lw=0.8, label="measured")
            ax.plot(t[j][m[j]], np.asarray(traj.torque)[j][m[j]], color="C0", lw=1.2, label="simulated")
            ax.set_ylabel("torque (N·m)")
            ax.set_title(f"{files[j]} ({modes[j]})", fontsize=9)
            ax.grid(alpha=0.3)
        axes[0, 0].legend(loc="upper right")
        axes[-1, 0].set_xlabel("time (s)")
        fig.tight_layout()
        _save(fig, out, "fig4_torque_fit.png", names, dpi=110)

    # Fig. 5: simulated vs measured velocity and torque, free and constrained
    pairs = [(j, md) for j, md in ((free[0] if free else None, "free"), (cons[0] if cons else None, "constrained")) if j is not None]
    if pairs:
        fig, axes = plt.subplots(2, len(pairs), figsize=(5.5 * len(pairs), 5.5), squeeze=False)
        for c, (j, md) in enumerate(pairs):
            for r_, (ch, unit) in enumerate((("motor_velocity", "rad/s"), ("torque", "N·m"))):
                ax = axes[r_, c]
                ax.plot(t[j][m[j]], np.asarray(getattr(full, ch))[j][m[j]], color="0.6", lw=0.8, label="measured")
                ax.plot(t[j][m[j]], np.asarray(getattr(traj, ch))[j][m[j]], color="C3", lw=1.2, ls="--", label="simulated")
                ax.set_ylabel(f"{ch.replace('_', ' ')} ({unit})")
                ax.set_xlabel("time (s)")
                ax.grid(alpha=0.3)
                ax.set_title(f"{md}: {files[j]}", fontsize=9)
        axes[0, 0].legend()
        fig.tight_layout()
        _save(fig, out, "fig5_simulation.png", names, dpi=110)
    return names


# ---- sensitivity ----

def sensitivity_figures(out, names, info, ok, files, modes, batch, sens, typical, fs_all, abl_traj) -> list[str]:
    """Figures of `hdjax sensitivity` into `out`: information heat map (parameters × experiments),
    time-resolved sensitivities of a typical test per mode, the correlation matrix and the paper's
    Figs. 6–7 (complete vs simplified model). Returns the file names written."""
    figs = []
    _information_heatmap(out, names, info, ok, files, modes, figs)
    _sensitivity_curves(out, names, files, batch, sens, typical, figs)
    _correlation_figure(out, names, fs_all, figs)
    if abl_traj is not None:
        _ablation_figures(out, files, batch, sens, typical, abl_traj, figs)
    return figs


def _information_heatmap(out, names, info, ok, files, modes, figs: list[str]) -> None:
    """Heat map of the information √F_kk (–, log scale), parameters × experiments, constrained
    first."""
    order = [j for j, m in enumerate(modes) if m == "constrained"] + [j for j, m in enumerate(modes) if m == "free"]
    n_cons = sum(m == "constrained" for m in modes)
    M = np.array([[info[k, j] if ok[j] and info[k, j] > 0 else np.nan for j in order] for k in range(len(names))])
    fig, ax = plt.subplots(figsize=(max(8, 0.22 * len(order) + 3), 4.8))
    finite = M[np.isfinite(M)]
    norm = LogNorm(vmin=max(finite.min(), finite.max() * 1e-8), vmax=finite.max()) if finite.size else None
    im = ax.imshow(np.ma.masked_invalid(M), aspect="auto", cmap="viridis", norm=norm, interpolation="nearest")
    ax.set_yticks(range(len(names)), names)
    ax.set_xticks(range(len(order)), [pathlib.Path(files[j]).stem for j in order], rotation=90, fontsize=6)
    if 0 < n_cons < len(order):
        ax.axvline(n_cons - 0.5, color="w", lw=2)
    ax.set_xlabel(f"experiment (constrained: first {n_cons}, free: last {len(order) - n_cons})")
    ax.set_ylabel("parameter p_k")
    ax.set_title("Information per experiment, √(Σ_t Σ_ch (∂y/∂ln p_k / σ_ch)²)")
    cb = fig.colorbar(im, ax=ax)
    cb.set_label("1 / relative SE of p_k alone (–), log scale")
    fig.tight_layout()
    _save(fig, out, "sensitivity_heatmap.png", figs, dpi=120)


def _sensitivity_curves(out, names, files, batch, sens, typical, figs: list[str]) -> None:
    """∂y/∂ln p over time (s) of torque (N·m) and motor velocity (rad/s) for a typical
    constrained and free experiment."""
    cols = [(m, typical[m]) for m in ("constrained", "free") if m in typical]
    if cols:
        t = np.asarray(batch.time)
        mask = np.asarray(batch.mask)
        S = np.asarray(sens.S)
        chans = ("torque", "motor_velocity")
        fig, axes = plt.subplots(len(chans), len(cols), figsize=(6.5 * len(cols), 6), squeeze=False, sharex="col")
        colors = plt.get_cmap("tab20")(np.linspace(0, 1, 20))
        for ci, (mode, j) in enumerate(cols):
            for ri, ch in enumerate(chans):
                ax = axes[ri, ci]
                c = CHANNELS.index(ch)
                for k, name in enumerate(names):
                    ax.plot(t[j][mask[j]], S[j, c][mask[j], k], lw=1, color=colors[(2 * k) % 20 + (k >= 10)],
                            ls="-" if k < 6 else "--", label=name)
                ax.set_ylabel(f"∂{CHANNEL_SYMBOL[ch]}/∂ln p ({CHANNEL_UNITS[ch]})")
                ax.grid(alpha=0.3)
                if ri == 0:
                    ax.set_title(f"{mode}: {files[j]}", fontsize=9)
            axes[-1, ci].set_xlabel("time (s)")
        axes[0, -1].legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, title="parameter")
        fig.tight_layout()
        _save(fig, out, "sensitivity_curves.png", figs, dpi=110)


def _correlation_figure(out, names, fs_all, figs: list[str]) -> None:
    """The noise-only correlation matrix of all 11 parameters (–)."""
    C = np.array(fs_all["correlation"], dtype=float)
    fig, ax = plt.subplots(figsize=(6.8, 5.8))
    im = ax.imshow(C, cmap="RdBu_r", vmin=-1, vmax=1)
    ax.set_xticks(range(len(names)), names, rotation=90)
    ax.set_yticks(range(len(names)), names)
    for a in range(len(names)):
        for b in range(len(names)):
            if np.isfinite(C[a, b]):
                ax.text(b, a, f"{C[a, b]:.2f}", ha="center", va="center", fontsize=6,
                        color="w" if abs(C[a, b]) > 0.6 else "k")
    ax.set_title("Parameter correlation (noise-only, all 11 free)")
    cb = fig.colorbar(im, ax=ax)
    cb.set_label("correlation coefficient (–)")
    fig.tight_layout()
    _save(fig, out, "correlation.png", figs, dpi=120)


def _ablation_figures(out, files, batch, sens, typical, abl_traj, figs: list[str]) -> None:
    """The paper's Fig. 6 (free) and Fig. 7 (constrained): measured vs complete vs simplified model,
    motor velocity (rad/s) and torque (N·m) over time (s), on the typical experiment of each mode."""
    t = np.asarray(batch.time)
    mask = np.asarray(batch.mask)
    y_c = np.asarray(sens.outputs)
    lanes = abl_traj["lanes"]
    for fname, mode, keys in (("fig6_free_ablation.png", "free", ("coulomb_zero", "viscous_zero")),
                              ("fig7_constrained_ablation.png", "constrained", ("K1_div10", "Tst_zero"))):
        if mode not in typical:
            continue
        j = typical[mode]
        fig, axes = plt.subplots(2, len(keys), figsize=(6.2 * len(keys), 5.8), squeeze=False, sharex=True)
        for ci, key in enumerate(keys):
            a = [i for i, ab in enumerate(ABLATIONS) if ab[0] == key][0]
            label = ABLATIONS[a][1]
            li = [i for i, (aa, jj) in enumerate(lanes) if aa == a and jj == j]
            for ri, (ch, c) in enumerate((("motor_velocity", 1), ("torque", 0))):
                ax = axes[ri, ci]
                meas = np.asarray(getattr(batch, ch))[j][mask[j]]
                ax.plot(t[j][mask[j]], meas, color="0.7", lw=2.4, label="measured")
                ax.plot(t[j][mask[j]], y_c[j, c][mask[j]], color="C0", lw=1.2, label="complete model")
                if li:
                    ok_l = bool(abl_traj["success"][li[0]])
                    ax.plot(t[j][mask[j]], abl_traj[ch][li[0]][mask[j]], color="C3", lw=1.2, ls="--",
                            label=label + ("" if ok_l else " (solve failed)"))
                ax.set_ylabel(f"{ch.replace('_', ' ')} ({CHANNEL_UNITS[ch]})")
                ax.grid(alpha=0.3)
                if ri == 0:
                    ax.set_title(f"{label}: {files[j]} ({mode})", fontsize=9)
                    ax.legend(fontsize=8)
            axes[-1, ci].set_xlabel("time (s)")
        fig.tight_layout()
        _save(fig, out, fname, figs, dpi=110)


# ---- tune ----

def tune_figures(out, traj, sim, ref_info, search, res, ilim, kind) -> list[str]:
    """Figures of `hdjax tune` into `out`: tracking and control effort of each controller against
    the reference, and the tuning cost history. Returns the file names written."""
    """tracking.png, control_effort.png, cost_history.png; `kind` ("bench" or "identified model")
    names what the validation ran on, in every title and legend."""
    names = []
    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    for j, (ax, info) in enumerate(zip(axes.flat, ref_info)):
        t = np.asarray(traj["tuned"]["time"])[j]
        ax.plot(t, np.asarray(traj["tuned"]["reference"])[j], "k--", lw=1.2, label="reference")
        for name in CONTROLLERS:
            ax.plot(t, np.asarray(traj[name]["measured_torque"])[j], color=COLORS[name], lw=0.5, alpha=0.35)
            ax.plot(t, np.asarray(traj[name]["torque"])[j], color=COLORS[name], lw=1.2, label=f"{LABELS[name]}: {kind}, true torque")
        ax.plot(t, np.asarray(sim.torque)[j], ":", color="tab:green", lw=1.3, label="tuned: tuning model, simulated")
        ax.set_title(f"{info['name'].replace('_', ' ')} ({info['amplitude']:.3g} N·m)")
        ax.set_ylabel("output torque (N·m)")
    for ax in axes[1]:
        ax.set_xlabel("time (s)")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"Torque tracking on the {kind}: baselines vs tuned (thin: measured torque)")
    fig.tight_layout()
    _save(fig, out, "tracking.png", names, dpi=110)

    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    for j, (ax, info) in enumerate(zip(axes.flat, ref_info)):
        t = np.asarray(traj["tuned"]["time"])[j]
        for name in CONTROLLERS:
            ax.plot(t, np.asarray(traj[name]["current"])[j], color=COLORS[name], lw=1.0, label=f"{LABELS[name]}: {kind}")
        ax.plot(t, np.asarray(sim.current)[j], ":", color="tab:green", lw=1.2, label="tuned: tuning model, simulated")
        ax.axhline(ilim, color="0.5", lw=0.8, ls="--", label="current limit")
        ax.axhline(-ilim, color="0.5", lw=0.8, ls="--")
        ax.set_title(info["name"].replace("_", " "))
        ax.set_ylabel("motor current (A)")
    for ax in axes[1]:
        ax.set_xlabel("time (s)")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"Control effort on the {kind}")
    fig.tight_layout()
    _save(fig, out, "control_effort.png", names, dpi=110)

    fig, ax = plt.subplots(figsize=(7, 4))
    sc = [c["cost"] for c in search]
    ns = len(sc)
    ax.semilogy(np.arange(-ns, 0), sc, "s", color="0.5", ms=4, label="start search (tuning model)")
    for k, name in enumerate(("relay_zn", "model_pi")):
        ax.axhline(search[k]["cost"], color=COLORS[name], ls="--", label=LABELS[name])
    for j, r in enumerate(res.runs):
        ax.semilogy(np.arange(len(r["history"])), r["history"], "o-", ms=3, label=f"BFGS start {j + 1}" + (" (kept)" if j == res.best_run else ""))
    ax.set_xlabel("candidate (<0: start search) / accepted BFGS iterate (-)")
    ax.set_ylabel("tuning cost (-)")
    ax.set_title("Tuning cost (model: plant sets x references + margin term)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    _save(fig, out, "cost_history.png", names, dpi=110)
    return names


# ---- diagnose ----

def diagnosis_figures(out, dataset, exps, files, d) -> list[str]:
    """Figures of `hdjax diagnose` into `out`: residual order spectra of the fitted paper model, and
    where effects were found, the torque residual before/after the extension and a locked test's
    hysteresis loop under both models. Returns the file names written."""
    names = []
    panels = _spectrum_panels(d.evidence)
    if panels:
        _spectra_figure(out, panels, d.findings, names)
    if d.findings and d.traces:
        batch = stack_experiments(exps)
        m = np.asarray(batch.mask)
        free = np.asarray(batch.free) > 0
        picks = most_improved_records(batch, d.traces)
        fig, axes = plt.subplots(len(picks), 1, figsize=(8.5, 2.8 * len(picks)), squeeze=False)
        for ax, (j, channel, reduction) in zip(axes[:, 0], picks):
            t = np.asarray(batch.time)[j][m[j]]
            meas = np.asarray(getattr(batch, channel))[j][m[j]]
            base = d.traces[f"{channel}_base"][j][m[j]]
            res = meas - base
            ax.plot(t, res, color="0.75", lw=0.6, label="measured − paper model")
            n_avg = max(3, int(0.01 * res.size) | 1)  # 1 % of the record, odd: a centred moving average
            ax.plot(t, np.convolve(res, np.ones(n_avg) / n_avg, mode="same"), color="0.25", lw=0.9,
                    label=f"measured − paper model, {n_avg}-sample moving average")
            ax.plot(t, d.traces[f"{channel}_extended"][j][m[j]] - base, color="C3", lw=1.1, label="extended − paper model")
            ax.set_ylabel(f"{_CHANNEL_LABELS[channel]} residual ({CHANNEL_UNITS[channel]})")
            ax.set_title(f"{files[j]} ({'free' if free[j] else 'constrained'}): the extension removes "
                         f"{100 * reduction:.0f} % of its squared {_CHANNEL_LABELS[channel]} residual", fontsize=9)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7, loc="upper right", framealpha=0.9)
        axes[-1, 0].set_xlabel("time (s)")
        fig.suptitle("Where the named effects matter most (per kind of test; base parameters of the final fit)", fontsize=10)
        fig.tight_layout()
        _save(fig, out, "residual_before_after.png", names, dpi=110)
        # hysteresis loop of a constrained test: torque against torsion, measured vs both models
        if (~free).any():
            # the locked record the extension changes most (the first locked record if it acts on free tests only)
            j = next((j for j, _, _ in picks if not free[j]), int(np.argmax(~free)))
            tw = d.traces["torsion_extended"][j][m[j]]
            fig, ax = plt.subplots(figsize=(6, 4.5))
            ax.plot(tw * 1e3, np.asarray(batch.torque)[j][m[j]], color="0.6", lw=0.6, label="measured torque")
            ax.plot(tw * 1e3, d.traces["torque_base"][j][m[j]], color="C0", lw=1.0, label="paper model")
            ax.plot(tw * 1e3, d.traces["torque_extended"][j][m[j]], color="C3", lw=1.0, ls="--", label="extended model")
            ax.set_xlabel("torsion Δθ of the extended model (mrad)")
            ax.set_ylabel("torque T (N·m)")
            ax.set_title(f"Hysteresis loop, {files[j]} (constrained)")
            ax.legend(fontsize=8)
            ax.grid(alpha=0.3)
            _save(fig, out, "hysteresis_before_after.png", names, dpi=110, bbox_inches="tight")
    return names


# ---- friction-only fit and diagnosis ----

def friction_velocity_figure(problem, pred, path, title, label="eq. 9"):
    """Friction torque (N·m) against velocity (rad/s): measured points and the model `pred`."""
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for e in range(problem.E):
        m = problem.mask[e]
        ax.plot(problem.v[e][m], problem.T[e][m], ".", ms=1, alpha=0.3, color="0.5",
                label="measured" if e == 0 else None)
        ax.plot(problem.v[e][m], pred[e][m], ".", ms=1, color="C3", label=f"model ({label})" if e == 0 else None)
    ax.set_xlabel("velocity (rad/s)")
    ax.set_ylabel("friction torque (N·m)")
    ax.set_title(title)
    ax.legend(markerscale=10)
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=110)
    plt.close(fig)
    return pathlib.Path(path)


def friction_heldout_time_figure(problem, fit, rows, path, max_panels: int = 4):
    """Held-out records against time: measured friction torque and the fitted model's prediction."""
    E = min(problem.E, max_panels)
    fig, axes = plt.subplots(E, 1, figsize=(9, 2.4 * E), squeeze=False)
    t = np.asarray(problem.data.time)
    for e in range(E):
        ax = axes[e, 0]
        m = problem.mask[e]
        ax.plot(t[e][m], problem.T[e][m], lw=0.6, color="0.4", label="measured")
        ax.plot(t[e][m], fit.prediction[1 + e][e][m], lw=0.8, color="C3", label="eq. 9 (fitted on first part alone)")
        test = rows.test[1 + e][e] > 0
        if test.any():
            ax.axvspan(t[e][test].min(), t[e][test].max(), color="C0", alpha=0.08, label="held out")
        ax.set_ylabel("friction torque (N·m)")
        ax.set_title(problem.files[e], fontsize=9)
        ax.legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("time (s)")
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=110)
    plt.close(fig)
    return pathlib.Path(path)


def friction_cv_figure(problem, d, path, max_panels: int = 4):
    """Friction-only diagnosis: measured friction torque and the held-out predictions of eq. 9 and of
    the extended model, one panel per record (at most `max_panels`)."""
    E = min(problem.E, max_panels)
    fig, axes = plt.subplots(E, 1, figsize=(9, 2.4 * E), squeeze=False)
    t = np.asarray(problem.data.time)
    names = " + ".join(f["effect"] for f in d.findings)
    for e in range(E):
        ax = axes[e, 0]
        m = problem.mask[e]
        ax.plot(t[e][m], problem.T[e][m], lw=0.6, color="0.4", label="measured")
        ax.plot(t[e][m], d.baseline.heldout[e][m], lw=0.8, color="C3", label="eq. 9, held out")
        if d.findings:
            ax.plot(t[e][m], d.final.heldout[e][m], lw=0.8, color="C2", label=f"eq. 9 + {names}, held out")
        ax.set_ylabel("friction torque (N·m)")
        ax.set_title(problem.files[e], fontsize=9)
        ax.legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("time (s)")
    fig.suptitle("cross-validated predictions (each sample predicted by the fold that held it out)", fontsize=9)
    fig.tight_layout()
    atomic_savefig(fig, path, dpi=110)
    plt.close(fig)
    return pathlib.Path(path)


_CHANNEL_LABELS = {"torque": "torque T", "motor_velocity": "motor velocity ωm", "output_position": "output position θo"}
_BALANCE_LABELS = {"e": "e (cogging, torque-sensor ripple)", "e*sign(w)": "e·sign(ω) (position-dependent friction)"}


def _spectrum_panels(evidence: dict) -> list[tuple[str, dict]]:
    """The order spectra of a diagnosis's evidence in units of their detection thresholds, one panel
    per kind of test: [(title, {series label: (amplitude / threshold per order, resolved per order)})].
    Output-error spectra use the per-record normalised amplitudes and the thresholds the loop used
    (`order_spectra_detection`); the torque-balance spectra the smaller of (amplitude / median) /
    `TB_MEDIAN_RATIO` and (amplitude / largest non-integer neighbour) / `TB_MAX_RATIO`, so that a bar
    above 1 is an order the loop screens in both."""
    spectra, detection = evidence.get("order_spectra", {}), evidence.get("order_spectra_detection", {})
    panels = []
    for mode, title in (("constrained", "locked tests: simulated − measured"), ("free", "free-motion tests: simulated − measured")):
        series = {}
        for channel, label in _CHANNEL_LABELS.items():
            key = f"{mode}/{channel} (per-record normalised)"
            if key in spectra and key in detection:
                info = detection[key]
                series[label] = (np.asarray(spectra[key], dtype=float) / info["threshold"], np.asarray(info["resolved"], dtype=bool))
        if series:
            panels.append((title, series))
    balance = evidence.get("torque_balance_spectra", {})
    series = {}
    for where, label in _BALANCE_LABELS.items():
        if where in balance:
            b = balance[where]
            ratio = np.minimum(np.asarray(b["over_median"]) / TB_MEDIAN_RATIO, np.asarray(b["over_max"]) / TB_MAX_RATIO)
            series[label] = (ratio, np.ones(ratio.shape, dtype=bool))
    if series:
        panels.append(("free-motion tests: motor torque balance e = Km·i − T/N − Tf(ω) − Jeff·dω/dt (measured signals)", series))
    return panels


def _spectra_figure(out, panels: list[tuple[str, dict]], findings: list, names: list[str]) -> None:
    """`residual_spectra.png`: each panel's spectra as bars in units of the detection threshold (a bar
    above the dashed line at 1 is a peak the loop screens), orders the tests do not resolve (less than
    one cycle of the wave generator) shaded and left out, and the orders of the named effects marked."""
    left_out = [title.split(":")[0] for title, series in panels if not any(r.any() for _, r in series.values())]
    panels = [(title, series) for title, series in panels if any(r.any() for _, r in series.values())]
    if not panels:
        return
    named = {}
    for f in findings:
        for k in f.get("orders") or []:
            named.setdefault(int(k), []).append(f["effect"])
    k = np.arange(1, MAX_ORDER + 1)
    fig, axes = plt.subplots(len(panels), 1, figsize=(8.5, 2.7 * len(panels) + 0.4), squeeze=False, sharex=True)
    for ax, (title, series) in zip(axes[:, 0], panels):
        w = 0.8 / len(series)
        top = 1.2
        unresolved = np.zeros(MAX_ORDER, dtype=bool)
        for j, (label, (ratio, resolved)) in enumerate(series.items()):
            unresolved |= ~resolved
            shown = np.where(resolved, ratio, np.nan)
            ax.bar(k + (j - (len(series) - 1) / 2) * w, shown, width=w, label=label, color=f"C{j}")
            if np.any(resolved):
                top = max(top, float(np.nanmax(shown)) * 1.15)
        for order in np.flatnonzero(unresolved) + 1:
            ax.axvspan(order - 0.45, order + 0.45, color="0.85", zorder=0)
        if unresolved.any():
            ax.text(0.99, 0.97, "grey: order not resolved (< 1 cycle)", transform=ax.transAxes, ha="right", va="top",
                    fontsize=7, color="0.3")
        for order, effects in named.items():
            if 1 <= order <= MAX_ORDER:
                ax.axvspan(order - 0.45, order + 0.45, color="gold", alpha=0.25, zorder=0)
                ax.text(order, top * 0.97, ", ".join(effects), ha="center", va="top", fontsize=7, rotation=0)
        ax.axhline(1.0, color="k", ls="--", lw=0.9, label="detection threshold")
        ax.set_ylim(0.0, top)
        ax.set_ylabel("amplitude / threshold (-)")
        ax.set_title(title, fontsize=9)
        ax.legend(fontsize=7, loc="upper left", framealpha=0.9)
        ax.grid(alpha=0.3, axis="y")
    axes[-1, 0].set_xticks(k)
    axes[-1, 0].set_xlabel("order (cycles per wave-generator turn)"
                           + "".join(f"\n{t}: not shown, no order resolved (the wave generator turns by less than one cycle)"
                                     for t in left_out))
    fig.suptitle("Residual order spectra of the fitted paper model" + (" (gold: orders of the named effects)" if named else ""),
                 fontsize=10)
    fig.tight_layout()
    _save(fig, out, "residual_spectra.png", names, dpi=110)


#: the channels `most_improved_records` compares (the diagnosis keeps base and extended traces of these)
_BEFORE_AFTER_CHANNELS = ("torque", "motor_velocity")


def most_improved_records(batch, traces: dict) -> list[tuple[int, str, float]]:
    """Per kind of test (locked first, then free), the record and channel where the extended model
    removes the largest share of the paper model's squared residual (in-sample, the final base
    parameters with and without the named effects): [(experiment index, channel, share)]. Channels
    are those with `<channel>_base` / `<channel>_extended` traces (torque, motor velocity)."""
    m = np.asarray(batch.mask)
    free = np.asarray(batch.free) > 0
    out = []
    for in_mode in (~free, free):
        best = None
        for j in np.flatnonzero(in_mode):
            for channel in _BEFORE_AFTER_CHANNELS:
                if f"{channel}_base" not in traces or not m[j].any():
                    continue
                meas = np.asarray(getattr(batch, channel))[j][m[j]]
                before = float(np.sum((meas - traces[f"{channel}_base"][j][m[j]]) ** 2))
                after = float(np.sum((meas - traces[f"{channel}_extended"][j][m[j]]) ** 2))
                share = 1.0 - after / before if before > 0 else 0.0
                if best is None or share > best[2]:
                    best = (int(j), channel, share)
        if best is not None:
            out.append(best)
    return out

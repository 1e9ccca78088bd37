"""The independent bench's time loop, compiled: `hdjax._testbench.independent._integrate`'s fine
steps written per record with scalars, for numba.

`_integrate` sets up the bench's constants and state in numpy and hands the loop to `run_steps`,
which runs fine steps n0 … n1 − 1 of every record. The arithmetic is `_integrate`'s, operation for
operation in the same order (the vectorised form stays as `independent._integrate_numpy`, the
reference a test compares this loop with, and the fallback where numba cannot be imported).

Why (2-core machine, 2026-12-08): the vectorised loop spends about 130 µs of numpy calls per
20 kHz step whatever the number of records, so making one 4 + 4-record dataset of 1.5 s (six
integrations: the operator's pilot runs, the effect's calibration, the final run) took 17 s; the
test suite makes about twenty such datasets, and the diagnosis benchmark one per seed.

This module imports numpy and numba only; nothing of hdjax or JAX.
"""

from __future__ import annotations

import math

import numpy as np

try:
    import numba
except ImportError:  # the vectorised loop (`independent._integrate_numpy`) is used instead
    numba = None

#: Whether the compiled loop is available.
AVAILABLE = numba is not None


def _jit(f):
    """`numba.njit` (compiled on first call, cached on disk beside this file, or in numba's user-wide
    cache where this folder is read-only; division by zero gives inf/nan as in numpy), or f itself
    without numba."""
    return f if numba is None else numba.njit(cache=True, error_model="numpy")(f)


#: State rows of `run_steps`' `S` array (B columns each).
STATE = ("thm", "wm", "tho", "wo", "ia", "integ", "volt", "zd", "zl", "Tprev", "idel", "Fprev", "zp", "rprev", "stk")
#: Scalar parameters (`P`) in order.
PARAMS = ("h", "iN", "Km", "Jh", "K1", "Tst", "Tss2", "Tvp", "Tvn", "Tsp", "Tsn", "Tssp1", "Tssn1", "brk_p", "brk_n",
          "ae", "be", "Kp", "KiH", "wb", "wr", "kappa", "hyst_sigma", "TH")  # fmt: skip
#: Switches (`F`, integers 0/1) in order.
FLAGS = ("current_loop", "hook", "cogging", "kinematic_error", "lost_motion", "nonlinear_stiffness",
         "rate_independent_hysteresis", "position_dependent_friction", "load_dependent_friction", "thermal_drift",
         "input_delay", "any_lug", "any_pre", "power_viscous")  # fmt: skip
#: Per-record rows (`C`) in order.
COLUMNS = ("iJl", "lug", "pre", "sig0", "sig1", "invA2", "d0", "dfr", "cogging", "kinematic_error", "lost_motion",
           "nonlinear_stiffness", "rate_independent_hysteresis", "position_dependent_friction",
           "load_dependent_friction")  # fmt: skip


@_jit
def _sign(x):
    if x > 0.0:
        return 1.0
    if x < 0.0:
        return -1.0
    return x  # 0 (or NaN), as np.sign


@_jit
def _periodic(k, phi, w, n, theta):
    """Σ_k w_k sin(k θ + φ_k) and its θ-derivative, summed in order (as numpy along axis 0)."""
    s = 0.0
    d = 0.0
    for i in range(n):
        ang = k[i] * theta + phi[i]
        s = s + w[i] * math.sin(ang)
        d = d + (w[i] * k[i]) * math.cos(ang)
    return s, d


@_jit
def _solve_pow(a, b, q):
    aq = abs(q)
    s = 2.0 * aq / (b + math.sqrt(b * b + 4.0 * a * aq) + 1e-300)
    return math.copysign(s * s, q)


@_jit
def _cands(F0, invA, wm, wo, tau, C, Tk, Kt, rho, rprev, Jh, iN, h, iJl, Tst, TH):
    W0 = (Jh * wm + tau - F0) * invA
    M = rho * iN * invA + h * iJl
    r = _solve_pow(1.0 + M * (TH * TH * h) * Kt, M * (TH * Tst), rho * W0 - wo - M * C)
    phi = Tst * math.copysign(math.sqrt(abs(r)), r)
    Teff = C + (TH * TH * h) * Kt * r + TH * phi
    return W0 - Teff * iN * invA, wo + h * iJl * Teff, Tk + (h * Kt) * (TH * r + (1.0 - TH) * rprev) + phi, r


@_jit
def run_steps(n0, n1, icmd, H, S, P, F, C, tf, pk, pphi, pw, pn, sub):
    """Fine steps n0 … n1 − 1 of every record, in place: `H` (5, steps + 1, B) histories T, wm, thm,
    tho, ia; `S` (len(STATE), B) state; `P`, `F`, `C` as `PARAMS`, `FLAGS`, `COLUMNS`; `tf` (steps, B)
    thermal viscous factor (or (1, B) unused); `pk`, `pphi`, `pw` (3, orders) periodic shapes of
    cogging, kinematic error and position-dependent friction (`pn` orders of each, the rest padding); `sub` fine steps per current-loop
    update."""
    h, iN, Km, Jh, K1, Tst, Tss2 = P[0], P[1], P[2], P[3], P[4], P[5], P[6]
    Tvp, Tvn, Tsp, Tsn, Tssp1, Tssn1, brk_p, brk_n = P[7], P[8], P[9], P[10], P[11], P[12], P[13], P[14]
    ae, be, Kp, KiH, wb, wr, kappa, hyst_sigma, TH = P[15], P[16], P[17], P[18], P[19], P[20], P[21], P[22], P[23]
    current_loop, hook, on_cog, on_ke, on_lm, on_nl, on_rih, on_pdf, on_ldf, on_td, on_id, any_lug, any_pre, pw_on = (
        F[0], F[1], F[2], F[3], F[4], F[5], F[6], F[7], F[8], F[9], F[10], F[11], F[12], F[13])
    ns = icmd.shape[0]
    B = icmd.shape[1]
    kc, phc, wc_, nc = pk[0], pphi[0], pw[0], pn[0]
    kk, phk, wk, nk = pk[1], pphi[1], pw[1], pn[1]
    kp_, php, wp, np_ = pk[2], pphi[2], pw[2], pn[2]
    F0 = np.zeros(4)
    invA = np.zeros(4)
    W = np.zeros(4)
    V = np.zeros(4)
    T = np.zeros(4)
    R_ = np.zeros(4)
    for b in range(B):
        thm, wm, tho, wo, ia, integ, volt, zd, zl = S[0, b], S[1, b], S[2, b], S[3, b], S[4, b], S[5, b], S[6, b], S[7, b], S[8, b]
        Tprev, idel, Fprev, zp_, rprev, stk = S[9, b], S[10, b], S[11, b], S[12, b], S[13, b], S[14, b] != 0.0
        iJl, lug, pre, sig0, sig1 = C[0, b], C[1, b] != 0.0, C[2, b] != 0.0, C[3, b], C[4, b]
        d0, dfr = int(C[6, b]), C[7, b]
        m_cog, m_ke, m_lm, m_nl, m_rih, m_pdf, m_ldf = C[8, b], C[9, b], C[10, b], C[11, b], C[12, b], C[13, b], C[14, b]
        invA[0], invA[1] = 1.0 / (Jh + TH * Tvp), 1.0 / (Jh + TH * Tvn)
        invA[2] = C[5, b]
        F0[2] = 0.0
        F0[3] = 0.0
        g = 0.0
        dl_ = 0.0
        tv = 0.0
        for n in range(n0, n1):
            # --- current loop and winding to t_{n+1}, back-EMF at ωm(t_n)
            if current_loop:
                if n % sub == 0:
                    e = icmd[n, b] - ia
                    integ = integ + KiH * e
                    volt = Kp * e + integ
                ia_new = ia * ae + (volt - Km * wm) * be
            else:
                ia_new = icmd[n, b] if hook else icmd[min(n + 1, ns - 1), b]
            H[4, n + 1, b] = ia_new
            if on_id:
                j0 = n + 1 - d0
                a0 = H[4, max(j0, 0), b] if j0 >= 0 else 0.0
                a1 = H[4, max(j0 - 1, 0), b] if j0 >= 1 else 0.0
                i1 = (1.0 - dfr) * a0 + dfr * a1
                tau = 0.5 * Km * (idel + i1)
                idel = i1
            else:
                tau = 0.5 * Km * (ia + ia_new)
            ia = ia_new
            if on_cog:
                tau = tau + m_cog * _periodic(kc, phc, wc_, nc, thm)[0]
            # --- torsion and elastic torque
            x = thm * iN - tho
            rho = iN
            if on_ke:
                e_, de = _periodic(kk, phk, wk, nk, thm)
                x = x + m_ke * e_
                rho = iN + m_ke * de
            Kt = K1
            if on_lm:
                x = x - min(max(x, -m_lm), m_lm)
                Kt = K1 if x != 0.0 else 0.0
            Tk = K1 * x
            if on_nl:
                Tk = Tk + m_nl * x**3
                Kt = Kt + 3.0 * m_nl * x * x
            if on_rih:
                Tk = Tk + m_rih * zd
            # --- friction
            aw = abs(wm)
            ex = math.exp(-((aw / Tss2) ** 2))
            cmod = 1.0
            if on_pdf:
                cmod = 1.0 + m_pdf * _periodic(kp_, php, wp, np_, thm)[0]
            load = m_ldf * abs(Tprev) * iN if on_ldf else 0.0
            fp = max(Tsp * cmod + Tssp1 * ex + load, 0.0)
            fn = max(Tsn * cmod + Tssn1 * ex + load, 0.0)
            F0[0], F0[1] = fp, -fn
            if any_pre:
                F0[2] = sig0 * zp_ if pre else 0.0
            tvf = tf[n, b] if on_td else 1.0
            if on_td:
                invA[0], invA[1] = 1.0 / (Jh + TH * Tvp * tvf), 1.0 / (Jh + TH * Tvn * tvf)
            if any_lug:
                sgn = _sign(wm)
                dl_ = sgn if sgn != 0 else (1.0 if zl >= 0 else -1.0)
                bp, bn = brk_p * cmod + load, brk_n * cmod + load
                bump = math.exp(-((aw / wb) ** 2))
                g = fp + (bp - fp) * bump if dl_ > 0 else fn + (bn - fn) * bump
                g = max(g, 0.05 * (bp if dl_ > 0 else bn))
                E = math.exp(-sig0 * aw * h / g)
                zss = sgn * g / sig0
                zp = zss + (zl - zss) * E
                cz = h * E
                F0[3] = sig0 * (zp - cz * wm) + sig1 * ex * (zp - zl) / h
                tv = (Tvp if dl_ > 0 else Tvn) * tvf
                invA[3] = 1.0 / (Jh + TH * tv + sig0 * cz)
            F0[0] += (1.0 - TH) * Tvp * tvf * wm
            F0[1] += (1.0 - TH) * Tvn * tvf * wm
            if any_lug:
                F0[3] += (1.0 - TH) * tv * wm
            if pw_on:
                dv = (wr ** (1.0 - kappa) * aw**kappa - aw) * _sign(wm) * tvf
                F0[0] += Tvp * dv
                F0[1] += Tvn * dv
                if any_lug:
                    F0[3] += (Tvp if dl_ > 0 else Tvn) * dv
            Cc = TH * Tk + (TH * (1.0 - TH) * h) * Kt * rprev + (1.0 - TH) * Tprev
            nr = 4 if any_lug else 3
            for i in range(nr):
                W[i], V[i], T[i], R_[i] = _cands(F0[i], invA[i], wm, wo, tau, Cc, Tk, Kt, rho, rprev, Jh, iN, h, iJl,
                                                 Tst, TH)  # fmt: skip
            Freq = tau - T[2] * iN
            if any_pre and pre:
                Freq = sig0 * (zp_ + h * W[2]) + sig1 * W[2]
            stick = (Freq <= brk_p * cmod + load) and (Freq >= -(brk_n * cmod + load))
            kn = 0 if Freq > 0 else 1
            mp = (not stk) and wm > 0
            mn = (not stk) and wm < 0
            stick = stick or (mp and kn == 0) or (mn and kn == 1)
            k = 0 if (mp and W[0] > 0) else (1 if (mn and W[1] < 0) else (2 if stick else kn))
            w_new, v_new, T_new, r_new = W[k], V[k], T[k], R_[k]
            if (mp and k == 1) or (mn and k == 0):  # a reversal through zero speed inside the step
                ko = 0 if wm > 0 else 1
                den = wm - W[ko]
                th = wm / den if den != 0 else 0.0
                th = min(max(th, 0.0), 1.0)
                f0p = max(Tsp + Tssp1, 0.0) * cmod + load
                f0n = max(Tsn + Tssn1, 0.0) * cmod + load
                visc = F0[k] - (fp if k == 0 else -fn)
                Fe = th * F0[ko] + (1.0 - th) * ((f0p if k == 0 else -f0n) + visc)
                w_new, v_new, T_new, r_new = _cands(Fe, invA[k], wm, wo, tau, Cc, Tk, Kt, rho, rprev, Jh, iN, h, iJl,
                                                    Tst, TH)  # fmt: skip
            if stk and k != 2:  # a breakaway inside the step
                bth = brk_p * cmod + load if Freq > 0 else -(brk_n * cmod + load)
                th = (bth - Fprev) / (Freq - Fprev if Freq != Fprev else 1.0)
                th = min(max(th, 0.0), 1.0)
                w_new = (1.0 - th) * w_new
                v_new = th * V[2] + (1.0 - th) * v_new
                T_new = th * T[2] + (1.0 - th) * T_new
                r_new = th * R_[2] + (1.0 - th) * r_new
            Fprev = Freq
            stk = k == 2
            if any_pre:
                if stk:
                    zp_ = zp_ + h * w_new
                else:
                    zp_ = (fp if w_new > 0 else (-fn if w_new < 0 else 0.0)) / sig0
            if any_lug:
                if lug:
                    w_new, v_new, T_new, r_new = W[3], V[3], T[3], R_[3]
                s2 = _sign(w_new)
                zss2 = s2 * g / sig0
                zl = zss2 + (zl - zss2) * math.exp(-sig0 * abs(w_new) * h / g) if lug else 0.0
            if on_rih:
                rr = rho * w_new - v_new
                s = _sign(rr)
                zd = s + (zd - s) * math.exp(-abs(rr) * h / hyst_sigma)
            thm = thm + h * (TH * w_new + (1.0 - TH) * wm)
            tho = tho + h * (TH * v_new + (1.0 - TH) * wo)
            wm, wo, Tprev, rprev = w_new, v_new, T_new, r_new
            H[0, n + 1, b], H[1, n + 1, b], H[2, n + 1, b], H[3, n + 1, b] = T_new, wm, thm, tho
        S[0, b], S[1, b], S[2, b], S[3, b], S[4, b], S[5, b], S[6, b], S[7, b], S[8, b] = thm, wm, tho, wo, ia, integ, volt, zd, zl
        S[9, b], S[10, b], S[11, b], S[12, b], S[13, b], S[14, b] = Tprev, idel, Fprev, zp_, rprev, 1.0 if stk else 0.0



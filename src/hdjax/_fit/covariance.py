"""Covariances of weighted least-squares fits, for both data kinds (`fit_parameters` on locked and
free records, the friction-only fits): the white-noise Gauss–Newton one, and a block (cluster)
sandwich that allows a misfit correlated in time, which is what a bench leaves when the model is
not exact (benchmarks/RESULTS.md, 2026-11-28)."""

from collections.abc import Callable

import numpy as np
from jaxtyping import Float

PINV_RCOND = 1e-13
"""Relative cut-off of the pseudo-inverse of JᵀJ in these covariances (directions below it get no
variance: see `null_directions`)."""

UNDETERMINED_SE_RTOL = 0.3
"""An estimate whose standard error is not finite or over this share of it is undetermined
(`poorly_determined`): the joint fit's rule (`fit.json → undetermined`) and the per-experiment fits'."""


def poorly_determined(value: float, se: float, rtol: float = UNDETERMINED_SE_RTOL) -> bool:
    """True when the standard error `se` is not finite or over `rtol` of the estimate `value`."""
    return bool(not np.isfinite(se) or (value != 0 and se / abs(value) > rtol))


def null_directions(J: Float[np.ndarray, "residual free"], rcond: float = PINV_RCOND) -> np.ndarray:
    """Per column of `J`, True where it lies along a null direction of JᵀJ (below `rcond`), which
    the pseudo-inverse of these covariances leaves out: there it reports a variance of about 0
    where the data carry no information, so such a standard error is infinite, not 0."""
    JtJ = J.T @ J
    return np.diag(np.linalg.pinv(JtJ, rcond=rcond) @ JtJ) <= 1 - 1e-6


def standard_errors(cov: Float[np.ndarray, "free free"], J: Float[np.ndarray, "residual free"]) -> np.ndarray:
    """The square roots of the diagonal of `cov` (a covariance of the fit with Jacobian `J`, in the
    same parameters), infinite along the null directions of JᵀJ (`null_directions`)."""
    return np.where(null_directions(J), np.inf, np.sqrt(np.clip(np.diag(cov), 0.0, None)))


def white_covariance(J: Float[np.ndarray, "residual free"], chi2: float) -> Float[np.ndarray, "free free"]:
    """The Gauss–Newton covariance σ²(JᵀJ)⁻¹ (σ² = `chi2`, the reduced χ²): right only when the
    residuals are white."""
    JtJ = J.T @ J
    try:
        cov = np.linalg.pinv(JtJ, rcond=PINV_RCOND) * chi2
    except np.linalg.LinAlgError:
        cov = np.full_like(JtJ, np.nan)
    return cov


def time_blocks(time: Float[np.ndarray, "exp time"], block_s: float) -> np.ndarray:
    """The block of each sample (int labels, shape of `time`): the samples of one record that lie
    in the same `block_s` seconds since its first sample share a label; records never share one."""
    k = np.floor((time - time[:, :1]) / block_s).astype(np.int64)
    k = np.clip(k, 0, None)  # padding repeats a record's times; its residuals are zero anyway
    return np.arange(time.shape[0])[:, None] * (int(k.max()) + 1) + k


def block_covariance(
    J: Float[np.ndarray, "residual free"], r: Float[np.ndarray, " residual"], blocks: np.ndarray
) -> tuple[Float[np.ndarray, "free free"], int]:
    """The cluster-robust (sandwich) covariance of a weighted least-squares fit whose residuals `r`
    are correlated within blocks of rows and independent between them: (JᵀJ)⁻¹ (Σ_b g_b g_bᵀ)
    (JᵀJ)⁻¹ · G/(G − 1), with g_b = J_bᵀ r_b summed over the rows of block b (`blocks`: one int label
    per row, e.g. `time_blocks` over every channel of a record) and G the number of blocks that
    hold data (rows whose residual is exactly 0, padding or unmeasured or weighted out, hold none).
    With white residuals of unit variance it is the Gauss–Newton covariance; where the model is not
    exact (a real bench) the misfit is correlated over the records' motion and this one is larger.
    Both data kinds use it (`fit_parameters`, the friction-only fits). Returns (covariance, G).

    Measured on clean independent-bench data (`tests/test_fit_bench.py`'s datasets, 2026-11-28): the
    nine fitted parameters were 0.3–59 Gauss–Newton standard errors from the bench's truth; with
    0.1 s blocks 0.1–3.9 of these, except the Stribeck amplitude Tssn1 on HD2 at 9.6 (a bias, not
    noise: eq. 9 cannot take the bench's stick–slip law, clipped at zero in that direction).
    An n/n_eff inflation from each record's lag-1 autocorrelation left them up to 32 away."""
    n_free = J.shape[1]
    has = r != 0.0
    _, block_of = np.unique(np.asarray(blocks).ravel()[has], return_inverse=True)
    G = int(block_of.max()) + 1 if block_of.size else 0
    g = np.zeros((G, n_free))
    np.add.at(g, block_of, J[has] * r[has, None])
    try:
        Hi = np.linalg.pinv(J.T @ J, rcond=PINV_RCOND)
    except np.linalg.LinAlgError:
        return np.full((n_free, n_free), np.nan), G
    return Hi @ (g.T @ g) @ Hi * (G / max(G - 1, 1)), G


def robust_covariance(
    J: Float[np.ndarray, "residual free"],
    r: Float[np.ndarray, " residual"],
    blocks: np.ndarray,
    fallback: Callable[[], np.ndarray],
) -> tuple[Float[np.ndarray, "free free"], str]:
    """`block_covariance`, or `fallback()` (called only then) when fewer than two blocks per fitted
    parameter hold data (too few for the sum of their outer products). Returns (covariance,
    "block_sandwich" or "fallback")."""
    cov, G = block_covariance(J, r, blocks)
    return (cov, "block_sandwich") if G >= 2 * J.shape[1] else (fallback(), "fallback")


def inflated_covariance(
    J: Float[np.ndarray, "residual free"], r: Float[np.ndarray, " residual"], record_residuals
) -> Float[np.ndarray, "free free"]:
    """The Gauss–Newton covariance s²(JᵀJ)⁻¹ (s² over the n non-zero rows of `r`) inflated by
    n / n_eff (`effective_samples` of `record_residuals`, at least p + 1): the friction-only fits'
    rule before 2026-11-28, now their fallback of `robust_covariance`."""
    n, p = int(np.count_nonzero(r)), J.shape[1]
    s2 = float(r @ r) / max(n - p, 1)
    return s2 * n / max(effective_samples(record_residuals), p + 1.0) * np.linalg.pinv(J.T @ J)


def effective_samples(residuals) -> float:
    """$n_{eff} = \\sum_e n_e (1-\\rho_e)/(1+\\rho_e)$ over records' residuals (an iterable of
    1-d arrays), $\\rho_e$ the lag-1 autocorrelation clipped to [0, 0.999]; records with fewer
    than 3 samples add nothing. Standard errors scale with $\\sqrt{n/n_{eff}}$."""
    n_eff = 0.0
    for re in residuals:
        if re.size < 3:
            continue
        d = re - re.mean()
        rho = float(np.clip(np.sum(d[1:] * d[:-1]) / max(np.sum(d * d), 1e-300), 0.0, 0.999))
        n_eff += re.size * (1 - rho) / (1 + rho)
    return n_eff

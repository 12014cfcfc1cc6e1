"""Prediction error metrics: per-step error, ADE, FDE, FDE p90, miss rate, ellipse coverage.

Plain NumPy on finished predictions; targets may be missing (masked), never invented.
"""

from __future__ import annotations

import numpy as np

MISS_THRESHOLD_M = 0.5


def errors_m(pred_xy_m: np.ndarray, target_xy_m: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(N, H) Euclidean errors [m]; NaN where the target is missing (mask False)."""
    err = np.linalg.norm(np.asarray(pred_xy_m) - np.asarray(target_xy_m), axis=-1)
    return np.where(mask, err, np.nan)


def summarize(err_m: np.ndarray, miss_threshold_m: float = MISS_THRESHOLD_M) -> dict:
    """Metrics from (N, H) errors [m] with NaN for missing targets.

    Returns a dict: ade_m (mean over every valid step), fde_m and fde_p90_m (final step, over the
    predictions whose final target exists), per_step_m (H,), miss_rate (final error >
    miss_threshold_m), n_predictions (predictions with a final target), n_targets (valid steps).
    """
    final = err_m[:, -1]
    final = final[np.isfinite(final)]
    valid = np.isfinite(err_m)
    with np.errstate(invalid="ignore"):
        per_step = [
            float(np.mean(c[np.isfinite(c)])) if np.any(np.isfinite(c)) else float("nan")
            for c in err_m.T
        ]
    return {
        "ade_m": float(np.mean(err_m[valid])) if valid.any() else float("nan"),
        "fde_m": float(np.mean(final)) if final.size else float("nan"),
        "fde_p90_m": float(np.percentile(final, 90)) if final.size else float("nan"),
        "per_step_m": per_step,
        "miss_rate": float(np.mean(final > miss_threshold_m)) if final.size else float("nan"),
        "n_predictions": int(final.size),
        "n_targets": int(valid.sum()),
    }


def track_frame_residuals(
    pred_xy_m: np.ndarray, target_xy_m: np.ndarray, heading_rad: np.ndarray
) -> np.ndarray:
    """Residuals target - prediction rotated into (along-track, cross-track) [m], shape (..., 2).

    heading_rad: the path heading at each predicted point (same leading shape).
    """
    d = np.asarray(target_xy_m) - np.asarray(pred_xy_m)
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)


def _kept(residuals_m: np.ndarray, mask: np.ndarray, k: int) -> np.ndarray:
    """Row indices of step k's residuals that count: present, and within 5 robust sigmas (a tag
    lost and re-found must not inflate an ellipse); none when fewer than 3 are present."""
    rows = np.flatnonzero(mask[:, k])
    if len(rows) < 3:
        return rows[:0]
    norm = np.linalg.norm(residuals_m[rows, k], axis=1)
    return rows[norm <= 5 * (1.4826 * np.median(norm) + 1e-9)]


def fit_covariance(residuals_m: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per-step 2x2 covariance (H, 2, 2) [m^2] of (N, H, 2) track-frame residuals.

    Zero-mean second moments (a bias is part of the error the ellipse must cover), without the
    outliers `_kept` leaves out; 1e-2 I where a step has fewer than 3 residuals.
    """
    h = residuals_m.shape[1]
    cov = np.zeros((h, 2, 2))
    for k in range(h):
        rows = _kept(residuals_m, mask, k)
        if len(rows) == 0:
            cov[k] = np.eye(2) * 1e-2
            continue
        r = residuals_m[rows, k]
        cov[k] = r.T @ r / len(r) + np.eye(2) * 1e-8
    return cov


MIN_MODEL_VAR_M2 = 1e-8


def _scaled_plus_constant(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """(c, q) >= 0 of the variance model E[y] = c x + q for squared residuals y of variance
    c x + q: Fisher scoring of the Gaussian likelihood (least squares weighted by 1 / (c x + q)^2,
    the variance of a squared Gaussian residual, iterated), on the boundary when the optimum
    is outside."""
    c, q = 0.0, max(float(np.mean(y)), MIN_MODEL_VAR_M2)
    for _ in range(20):
        w = 1.0 / np.square(c * x + q)
        a = np.array([[np.sum(w * x * x), np.sum(w * x)], [np.sum(w * x), np.sum(w)]])
        b = np.array([np.sum(w * x * y), np.sum(w * y)])
        try:
            c_new, q_new = np.linalg.solve(a, b)
        except np.linalg.LinAlgError:  # every x equal: q alone
            c_new, q_new = -1.0, 0.0
        if c_new < 0.0:  # no state variance in it: q alone
            c_new, q_new = 0.0, np.sum(w * y) / np.sum(w)
        elif q_new < MIN_MODEL_VAR_M2:  # all of it scales with the state variance
            c_new, q_new = np.sum(w * x * y) / np.sum(w * x * x), MIN_MODEL_VAR_M2
        done = abs(c_new - c) <= 1e-6 * (abs(c) + 1e-12) and abs(q_new - q) <= 1e-6 * q
        c, q = float(c_new), max(float(q_new), MIN_MODEL_VAR_M2)
        if done:
            break
    return c, q


def fit_variance_model(
    residuals_m: np.ndarray, state_var_m2: np.ndarray, mask: np.ndarray
) -> dict[str, np.ndarray]:
    """The per-prediction uncertainty's fitted values: per step and axis the variance of a
    residual is `state_scale` x its state estimate's variance + `model_var_m2` (the model's own
    error), with `correlation` between the axes per step.

    Args:
        residuals_m: (N, H, 2) track-frame residuals [m] (along, cross).
        state_var_m2: (N, H, 2) variance [m^2] each prediction's state estimate causes
            (`fpe_jax.model.estimate_variance`).
        mask: (N, H) which residuals exist.

    Returns state_scale (H, 2), model_var_m2 (H, 2) [m^2] and correlation (H,) (of the
    residuals normalised by their fitted standard deviations, clipped to +-0.99), fitted on
    the residuals `_kept` leaves.
    """
    h = residuals_m.shape[1]
    scale, model, corr = np.zeros((h, 2)), np.full((h, 2), 1e-2), np.zeros(h)
    for k in range(h):
        rows = _kept(residuals_m, mask, k)
        if len(rows) == 0:
            continue
        r, x = residuals_m[rows, k], state_var_m2[rows, k]
        for a in range(2):
            scale[k, a], model[k, a] = _scaled_plus_constant(x[:, a], r[:, a] ** 2)
        z = r / np.sqrt(scale[k] * x + model[k])
        corr[k] = np.clip(
            np.sum(z[:, 0] * z[:, 1]) / np.sqrt(np.sum(z * z, axis=0).prod()), -0.99, 0.99
        )
    return {"state_scale": scale, "model_var_m2": model, "correlation": corr}


def row_covariance(state_var_m2: np.ndarray, state_scale, model_var_m2, correlation) -> np.ndarray:
    """(N, H, 2, 2) track-frame covariance [m^2] of each prediction from its state estimate's
    variance (N, H, 2) and the fitted values of `fit_variance_model`."""
    var = np.asarray(state_scale) * state_var_m2 + np.asarray(model_var_m2)
    along, cross = var[..., 0], var[..., 1]
    off = np.asarray(correlation) * np.sqrt(along * cross)
    return np.stack([np.stack([along, off], -1), np.stack([off, cross], -1)], -2)


def coverage(residuals_m: np.ndarray, mask: np.ndarray, cov_m2: np.ndarray) -> dict:
    """Fraction of residuals (N, H, 2) inside the 1- and 2-sigma ellipses of cov: per step
    (H, 2, 2), or per prediction (N, H, 2, 2).

    For a 2-D Gaussian the ideal fractions are 1 - exp(-1/2) = 39.3 % and 1 - exp(-2) = 86.5 %.
    """
    inv = np.broadcast_to(np.linalg.inv(cov_m2), residuals_m.shape + (2,))
    d2 = np.einsum("nhi,nhij,nhj->nh", residuals_m, inv, residuals_m)
    d2 = d2[mask]
    return {
        "coverage_1sigma": float(np.mean(d2 <= 1.0)) if d2.size else float("nan"),
        "coverage_2sigma": float(np.mean(d2 <= 4.0)) if d2.size else float("nan"),
        "ideal_1sigma": float(1 - np.exp(-0.5)),
        "ideal_2sigma": float(1 - np.exp(-2.0)),
    }

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


def fit_covariance(residuals_m: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per-step 2x2 covariance (H, 2, 2) [m^2] of (N, H, 2) track-frame residuals.

    Zero-mean second moments (a bias is part of the error the ellipse must cover); residuals
    beyond 5 robust sigmas (tag lost and re-found) are left out so they do not inflate it.
    """
    h = residuals_m.shape[1]
    cov = np.zeros((h, 2, 2))
    for k in range(h):
        r = residuals_m[mask[:, k], k]
        if len(r) < 3:
            cov[k] = np.eye(2) * 1e-2
            continue
        norm = np.linalg.norm(r, axis=1)
        scale = 1.4826 * np.median(norm) + 1e-9
        r = r[norm <= 5 * scale]
        cov[k] = r.T @ r / len(r) + np.eye(2) * 1e-8
    return cov


def coverage(residuals_m: np.ndarray, mask: np.ndarray, cov_m2: np.ndarray) -> dict:
    """Fraction of residuals inside the 1- and 2-sigma ellipses of cov (H, 2, 2).

    For a 2-D Gaussian the ideal fractions are 1 - exp(-1/2) = 39.3 % and 1 - exp(-2) = 86.5 %.
    """
    inv = np.linalg.inv(cov_m2)  # (H, 2, 2)
    d2 = np.einsum("nhi,hij,nhj->nh", residuals_m, inv, residuals_m)
    d2 = d2[mask]
    return {
        "coverage_1sigma": float(np.mean(d2 <= 1.0)) if d2.size else float("nan"),
        "coverage_2sigma": float(np.mean(d2 <= 4.0)) if d2.size else float("nan"),
        "ideal_1sigma": float(1 - np.exp(-0.5)),
        "ideal_2sigma": float(1 - np.exp(-2.0)),
    }

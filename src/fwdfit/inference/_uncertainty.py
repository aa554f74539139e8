"""Uncertainties at the optimum: covariance from the residual Jacobian, propagated to T_att."""

from __future__ import annotations

import numpy as np


def covariance(jacobian: np.ndarray, chi2: float, dof: int, sigma_from_data: bool) -> np.ndarray:
    """Covariance (n, n) of the free values from the Jacobian (N, n) of the normalised residuals.

    With sigma estimated from the data's scatter (no T_err), the covariance is scaled by
    the reduced chi-square.
    """
    curvature = jacobian.T @ jacobian
    result = np.linalg.pinv(curvature, rcond=1e-12, hermitian=True)
    return result * chi2 / max(dof, 1) if sigma_from_data else result


def errors_and_correlation(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """1-sigma errors (n,) and correlation matrix (n, n) of a covariance."""
    errors = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    outer = np.outer(errors, errors)
    return errors, np.divide(cov, outer, out=np.zeros_like(cov), where=outer > 0)


def band(att_jacobian: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """1-sigma band (N,) of a prediction with Jacobian (N, n) under covariance (n, n)."""
    return np.sqrt(np.clip(np.einsum("ij,jk,ik->i", att_jacobian, cov, att_jacobian), 0.0, None))


def central_differences(predict, values: np.ndarray, steps: np.ndarray):
    """Jacobians (N, n) of both outputs of predict(rows (m, n)) -> (A (m, N), B (m, N)) at values (n,)."""
    n = len(values)
    shifts = np.eye(n) * steps[:, None]
    A, B = predict(np.concatenate([values + shifts, values - shifts]))
    return ((A[:n] - A[n:]) / (2 * steps[:, None])).T, ((B[:n] - B[n:]) / (2 * steps[:, None])).T

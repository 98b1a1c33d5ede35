"""Quality figures of a simulated (output-error) model, computed like MATLAB's ``compare``/``aic``.

All functions take measured outputs ``y`` and simulated outputs ``yhat`` of shape ``(N, ny)``
(a 1-D array is treated as one output) in the outputs' own units.

- fit %  (MATLAB ``compare``, NRMSE): ``100 * (1 - ||y - yhat|| / ||y - mean(y)||)`` per output.
- RMSE: ``sqrt(mean((y - yhat)^2))`` per output, in the output's unit.
- loss (MATLAB ``LossFcn``): ``det(E^T E / N)`` with ``E = y - yhat`` (units squared, product).
- FPE (MATLAB ``fpe``): ``loss * (1 + d/N) / (1 - d/N)`` with ``d`` estimated parameters.
- AIC, BIC: ``-2 log L + 2 d`` and ``-2 log L + d log N`` with the Gaussian
  ``-2 log L = N log det(E^T E / N) + N ny (1 + log 2 pi)``. AIC equals MATLAB's raw AIC;
  MATLAB's BIC differs by a constant that cancels in every comparison made here.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


def _pair(y: ArrayLike, yhat: ArrayLike) -> tuple[Array, Array]:
    a = np.asarray(y, dtype=float)
    b = np.asarray(yhat, dtype=float)
    if a.ndim == 1:
        a = a[:, None]
    if b.ndim == 1:
        b = b[:, None]
    if a.shape != b.shape:
        raise ValueError(f"yhat: expected shape {a.shape}, got {b.shape}")
    if a.ndim != 2 or a.shape[0] < 2:
        raise ValueError(f"y: expected shape (N >= 2, ny), got {a.shape}")
    return a, b


def fit_percent(y: ArrayLike, yhat: ArrayLike) -> Array:
    """MATLAB ``compare`` fit per output [%], shape (ny,).

    ``100 * (1 - ||y - yhat|| / ||y - mean(y)||)``; 100 is perfect, 0 is as good as the mean,
    negative is worse than the mean. An output that is constant gives ``-inf`` unless matched.
    """
    a, b = _pair(y, yhat)
    num = np.linalg.norm(a - b, axis=0)
    den = np.linalg.norm(a - a.mean(axis=0), axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = 100.0 * (1.0 - num / den)
    out = np.where((den == 0.0) & (num == 0.0), 100.0, out)
    return np.asarray(out, dtype=float)


def rmse(y: ArrayLike, yhat: ArrayLike) -> Array:
    """Root-mean-square error per output (output units), shape (ny,)."""
    a, b = _pair(y, yhat)
    return np.asarray(np.sqrt(np.mean((a - b) ** 2, axis=0)))


def loss(y: ArrayLike, yhat: ArrayLike) -> float:
    """MATLAB's loss ``det(E^T E / N)``; for one output the mean squared error."""
    a, b = _pair(y, yhat)
    e = a - b
    return float(np.linalg.det(e.T @ e / e.shape[0]))


def fpe(loss_value: float, n_samples: int, n_params: int) -> float:
    """Akaike's final prediction error ``loss (1 + d/N) / (1 - d/N)``; ``inf`` when d >= N."""
    if n_params >= n_samples:
        return math.inf
    return float(loss_value * (1.0 + n_params / n_samples) / (1.0 - n_params / n_samples))


def neg2_log_likelihood(loss_value: float, n_samples: int, n_outputs: int) -> float:
    """Gaussian ``-2 log L = N log(loss) + N ny (1 + log 2 pi)``."""
    if loss_value <= 0.0:
        return -math.inf
    return float(n_samples * math.log(loss_value)
                 + n_samples * n_outputs * (1.0 + math.log(2.0 * math.pi)))


def aic(loss_value: float, n_samples: int, n_outputs: int, n_params: int) -> float:
    """Raw AIC ``-2 log L + 2 d`` (MATLAB ``aic(sys)``)."""
    return neg2_log_likelihood(loss_value, n_samples, n_outputs) + 2.0 * n_params


def bic(loss_value: float, n_samples: int, n_outputs: int, n_params: int) -> float:
    """BIC ``-2 log L + d log N``."""
    return neg2_log_likelihood(loss_value, n_samples, n_outputs) + n_params * math.log(n_samples)


@dataclass(frozen=True)
class Figures:
    """Figures of one model on one data set (several segments pooled).

    Attributes:
        output_names: names of the outputs, length ny.
        fit_percent: MATLAB ``compare`` fit per output [%] (pooled norms over segments).
        rmse: RMSE per output [output units].
        mse: mean squared error per output.
        loss: ``det(E^T E / N)``.
        fpe, aic, bic: see module docstring (``n_params`` counts every estimated number).
        n_samples: pooled sample count N.
        n_params: estimated parameters d.
    """

    output_names: tuple[str, ...]
    fit_percent: tuple[float, ...]
    rmse: tuple[float, ...]
    mse: tuple[float, ...]
    loss: float
    fpe: float
    aic: float
    bic: float
    n_samples: int
    n_params: int

    def as_dict(self) -> dict[str, object]:
        """JSON-ready dictionary (per-output figures keyed by output name)."""
        return {
            "fit_percent": dict(zip(self.output_names, self.fit_percent, strict=True)),
            "rmse": dict(zip(self.output_names, self.rmse, strict=True)),
            "mse": dict(zip(self.output_names, self.mse, strict=True)),
            "loss": self.loss, "fpe": self.fpe, "aic": self.aic, "bic": self.bic,
            "n_samples": self.n_samples, "n_params": self.n_params,
        }

    @property
    def mean_fit(self) -> float:
        """Mean fit over outputs [%]."""
        return float(np.mean(self.fit_percent))


def figures(ys: Sequence[ArrayLike], yhats: Sequence[ArrayLike], n_params: int,
            output_names: Sequence[str]) -> Figures:
    """Pool several segments and compute :class:`Figures`.

    Fit % uses each segment's own mean (``||y - mean(y)||`` summed in quadrature over segments),
    so a pooled figure equals ``compare`` on one segment.

    Args:
        ys, yhats: measured and simulated outputs per segment, each shape (N_i, ny).
        n_params: number of estimated parameters d.
        output_names: ny names.
    """
    if len(ys) != len(yhats) or not ys:
        raise ValueError(f"yhats: expected {len(ys)} segments (>= 1), got {len(yhats)}")
    pairs = [_pair(y, yh) for y, yh in zip(ys, yhats, strict=True)]
    ny = pairs[0][0].shape[1]
    if len(output_names) != ny:
        raise ValueError(f"output_names: expected {ny} names, got {len(output_names)}")
    num = np.sqrt(sum(np.sum((a - b) ** 2, axis=0) for a, b in pairs))
    den = np.sqrt(sum(np.sum((a - a.mean(axis=0)) ** 2, axis=0) for a, _ in pairs))
    with np.errstate(divide="ignore", invalid="ignore"):
        fit = np.where(den > 0, 100.0 * (1.0 - num / np.where(den > 0, den, 1.0)), -np.inf)
    e = np.vstack([a - b for a, b in pairs])
    n = e.shape[0]
    mse = np.mean(e ** 2, axis=0)
    lv = float(np.linalg.det(e.T @ e / n))
    return Figures(
        output_names=tuple(output_names),
        fit_percent=tuple(float(v) for v in fit),
        rmse=tuple(float(v) for v in np.sqrt(mse)),
        mse=tuple(float(v) for v in mse),
        loss=lv, fpe=fpe(lv, n, n_params), aic=aic(lv, n, ny, n_params),
        bic=bic(lv, n, ny, n_params), n_samples=n, n_params=n_params,
    )


def parameter_std(jac: ArrayLike, residual: ArrayLike, n_params: int | None = None) -> Array:
    """Standard deviations of least-squares parameters from the Jacobian.

    ``cov = s^2 (J^T J)^+`` with ``s^2 = ||r||^2 / (m - p)``; the pseudo-inverse gives ``inf``
    for directions the data do not determine (singular values below ``1e-10`` of the largest).
    This assumes white residuals; coloured residuals make the figures optimistic.

    Args:
        jac: Jacobian of the residual vector, shape (m, p).
        residual: residual vector, shape (m,).
        n_params: p used in ``m - p`` (defaults to the Jacobian's column count).

    Returns:
        Standard deviations, shape (p,), in the parameters' units.
    """
    J = np.asarray(jac, dtype=float)
    r = np.asarray(residual, dtype=float).ravel()
    if J.ndim != 2 or J.shape[0] != r.size:
        raise ValueError(f"jac: expected shape ({r.size}, p), got {J.shape}")
    m, p = J.shape
    dof = max(m - (p if n_params is None else n_params), 1)
    s2 = float(r @ r) / dof
    _, sv, vt = np.linalg.svd(J, full_matrices=False)
    if sv.size == 0 or sv[0] == 0.0:
        return np.full(p, np.inf)
    keep = sv > 1e-10 * sv[0]
    inv = np.where(keep, 1.0 / np.where(keep, sv, 1.0) ** 2, 0.0)
    var = s2 * np.sum((vt.T ** 2) * inv, axis=1)
    # A parameter with a component in a dropped direction is not determined.
    dropped = ~keep
    if np.any(dropped):
        undetermined = np.any(np.abs(vt[dropped].T) > 1e-6, axis=1)
        var = np.where(undetermined, np.inf, var)
    return np.asarray(np.sqrt(var))


def rate_upper_bound(events: int, n: int, level: float = 0.95) -> float:
    """One-sided Clopper-Pearson upper bound on a rate from ``events`` of ``n`` trials (false
    effects over clean plants, extra terms over refits): 1 when every trial had the event.

    Raises:
        ValueError: ``n < 1`` or ``events`` outside ``[0, n]``.
    """
    from scipy import stats

    if n < 1 or not 0 <= events <= n:
        raise ValueError(f"rate_upper_bound: expected 0 <= events <= n, n >= 1, got "
                         f"events {events}, n {n}")
    if events >= n:
        return 1.0
    return float(stats.beta.ppf(level, events + 1, n - events))

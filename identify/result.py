"""The result of a fit: values, standard errors, correlations and noise levels at the optimum."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from . import profile, robust
from .least_squares import covariance
from .problem import Problem


@dataclasses.dataclass
class Result:
    labels: list
    values: dict  # name -> value (list or float)
    standard_errors: dict
    correlation: list  # (p, p) of the fitted unknowns, in `labels` order (log space for log unknowns)
    sigma: list  # noise estimates: position (m), angle (rad)
    loss: float  # final reduced chi-square
    rms: list  # RMS residual per column, in m, m, rad
    iterations: int = 0
    wall_s: float = 0.0
    converged: bool = True
    history: list = dataclasses.field(default_factory=list)  # loss per iteration (all stages)
    stages: list = dataclasses.field(default_factory=list)  # per stage: window, iterations, final loss
    message: str = ""
    outliers: list = dataclasses.field(default_factory=list)  # times (s) of frames thrown off (`robust.spikes`)
    # the model error of the values (`discretisation`): how far each moved on the last grid
    # refinement and with a tenth of the Newton tolerance; the model the values come from
    discretisation_errors: dict = dataclasses.field(default_factory=dict)
    tolerance_errors: dict = dataclasses.field(default_factory=dict)
    model: dict = dataclasses.field(default_factory=dict)  # nodes, dt, tol
    refinements: list = dataclasses.field(default_factory=list)
    # name -> the loss's profile along each measured value at the fit's grid (`profile.report`)
    profiles: dict = dataclasses.field(default_factory=dict)
    # the loss's rise one standard error along its least determined direction (`valley.check`)
    valley: dict = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    def statistical_error(self, name):
        """The statistical error of ``name``: its standard error, widened where a profile
        (`profile.widening`) puts the 68 % interval farther from the fit's value than the
        standard error says (a valley that curves or flattens within a standard error)."""
        se = self.standard_errors[name]
        entries = self.profiles.get(name)
        if not entries:
            return se
        wide = [profile.widening(e) for e in (entries if isinstance(entries, list) else [entries])]
        return (np.asarray(se, float) * wide).tolist() if isinstance(entries, list) else float(se * wide[0])

    def uncertainty(self, name):
        """The statistical (`statistical_error`) and discretisation errors of ``name`` combined
        (root sum of squares)."""
        return np.hypot(self.statistical_error(name), self.discretisation_errors.get(name, 0.0))


def summarize(problem: Problem, theta, J, r, t_end=None, **info) -> Result:
    """The `Result` at an optimum ``theta`` (with its Jacobian ``J`` and residuals ``r`` over the
    window up to ``t_end``): values, standard errors from the Gauss-Newton covariance rescaled by
    the reduced chi-square, correlations, and the pattern frame derived with its errors."""
    keep = np.asarray(problem.window(t_end)[0]) > 0
    m, p = problem.counted(t_end), theta.size
    chi2 = float(r @ r) / max(m - p, 1)
    values, errors, corr = _errors(problem, theta, covariance(J) * chi2)
    res = (np.asarray(robust.unhuber(r, problem.huber)).reshape(-1, 3) * problem.sigma)[keep]  # before the Huber loss
    return Result(
        labels=problem.labels(),
        values=values,
        standard_errors=errors,
        correlation=corr.tolist(),
        sigma=[float(problem.sigma[0]), float(problem.sigma[2])],
        loss=chi2,
        rms=np.sqrt(np.mean(res**2, axis=0)).tolist(),
        **info,
    )


def noise_covariance(problem: Problem, J, sigma) -> np.ndarray:
    """The covariance of theta at an optimum whose Jacobian ``J`` is whitened with
    ``problem.sigma``, when the columns' noise levels are ``sigma`` (m, m, rad) instead: the fit
    weighted each column with its own level, so the covariance is the sandwich
    A^-1 J^T D J A^-1 (A = J^T J; D, per row, the new variance over the weighting one)."""
    A = covariance(J)
    d = np.tile((np.asarray(sigma, float) / problem.sigma) ** 2, J.shape[0] // 3)
    return A @ ((J.T * d) @ J) @ A


def with_noise(result: Result, problem: Problem, theta, J, sigma) -> tuple[Result, np.ndarray]:
    """(``result`` with its standard errors, correlations and noise levels for the noise levels
    ``sigma`` (`noise_covariance`), the standard errors of theta)."""
    cov = noise_covariance(problem, J, sigma)
    _, errors, corr = _errors(problem, theta, cov)
    out = dataclasses.replace(result, standard_errors=errors, correlation=corr.tolist(), sigma=[float(sigma[0]), float(sigma[2])])
    return out, np.sqrt(np.maximum(np.diag(cov), 0.0))


def _errors(problem: Problem, theta, cov) -> tuple[dict, dict, np.ndarray]:
    """(values, standard errors, correlation) of the unknowns at ``theta`` whose covariance is
    ``cov``, with the pattern frame derived and its errors by the delta method."""
    se_theta = np.sqrt(np.maximum(np.diag(cov), 0.0))
    corr = cov / np.outer(se_theta, se_theta)
    vals = problem.to_values(jnp.asarray(theta))
    values, errors = {}, {}
    for u in problem.unknowns:
        v = np.atleast_1d(np.asarray(vals[u.name], float))
        s = se_theta[problem.slices[u.name]] * (v if u.log else u.unit)  # d exp(x) = exp(x) dx
        values[u.name] = v.tolist() if u.size > 1 else float(v[0])
        errors[u.name] = s.tolist() if u.size > 1 else float(s[0])
    frame, G = problem.frame(theta)
    frame_se = np.sqrt(np.maximum(np.diag(G @ cov @ G.T), 0.0))
    values.update(frame_offset=frame[:2].tolist(), frame_rotation=float(frame[2]))
    errors.update(frame_offset=frame_se[:2].tolist(), frame_rotation=float(frame_se[2]))
    return values, errors, corr

"""Worst-case search over a distribution's standard variates (inside its bounds, [0, 1]^D).

- `gradient_ascent`: batched multi-start projected gradient ascent on the smooth failure margin
  (`MarginProblem.value_and_grad`): optax Adam steps on the free variates (continuous, range not
  a single value; discrete ones keep each start's values), each followed by the projection onto
  the bounds (clip to [0, 1]). Stops at the first iterate whose exact margin is > 0 (a failing
  case) unless told to go on.
- `cmaes_search`: the gradient-free baseline, CMA-ES (the ``cmaes`` package, bounds [0, 1] on the
  same free variates), one population per generation evaluated as one batch on the fast path,
  the population size equal to the number of starts (at least 4), from the first start, same
  budget.
- `most_likely_failure`: from a failing case u_f, the failing point of highest nominal density
  along the ray from the nominal point in standard-normal space (z = Phi^-1(u); the density falls
  with |z|): the smallest t in (0, 1] with margin(t z_f) > 0, by a batched grid then bisection.
  An upper bound of the distance of the most likely failure (the design point), not its
  optimum.
- `design_point_search`: the most likely failure itself: minimise |z|^2 over the free variates
  subject to a failing margin, by SciPy's SLSQP with the smooth margin's gradient as the
  constraint's Jacobian, started from a failing point (the ray's); returns the failing point
  of smallest |z| seen, re-checked by a forward solve (`DesignPoint`).

Budgets and counts are in simulations (a gradient evaluation is one simulation with its
adjoint; its cost in seconds is reported beside).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import optax
from scipy import optimize, stats

from ._estimators import to_normal, to_unit
from ._problem import MarginProblem


@dataclass
class SearchResult:
    """Outcome of a worst-case search.

    Attributes:
        method: "gradient" or "cmaes".
        best_u: variates of the largest exact margin found (D,); best_margin: that margin.
        first_failure: simulations used when the first failing case was found (None: none).
        simulations: simulations used in all; seconds: wall time [s].
        history: (simulations so far, best exact margin so far) after each iteration.
        failing_u: variates of every failing case found (k, D).
    """

    method: str
    best_u: np.ndarray
    best_margin: float
    first_failure: int | None
    simulations: int
    seconds: float
    history: list = field(default_factory=list)
    failing_u: np.ndarray | None = None

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "best_margin": self.best_margin,
            "first_failure_simulations": self.first_failure,
            "simulations": self.simulations,
            "seconds": self.seconds,
            "history": self.history,
        }


def gradient_ascent(
    problem: MarginProblem,
    starts: np.ndarray,
    budget: int,
    learning_rate: float = 0.05,
    stop_at_failure: bool = True,
) -> SearchResult:
    """Projected multi-start Adam ascent of the smooth margin (module docstring) from
    ``starts`` (n, D) in [0, 1]^D, at most ``budget`` simulations (n per iteration)."""
    t0 = time.perf_counter()
    u = np.clip(np.asarray(starts, dtype=np.float64), 0.0, 1.0)
    free = problem.free
    opt = optax.adam(learning_rate)
    state = opt.init(u)
    used, best_u, best, first, history, failing = 0, u[0], -np.inf, None, [], []
    while used + u.shape[0] <= budget:
        value, grad, exact = problem.value_and_grad(u)
        used += u.shape[0]
        i = int(np.argmax(exact))
        if exact[i] > best:
            best, best_u = float(exact[i]), u[i].copy()
        history.append((used, best))
        if np.any(exact > 0):
            failing.append(u[exact > 0])
            if first is None:
                first = used
            if stop_at_failure:
                break
        step, state = opt.update(-np.where(free, grad, 0.0), state)  # ascent
        u = np.clip(u + np.asarray(step), 0.0, 1.0)
    return SearchResult(
        "gradient",
        best_u,
        best,
        first,
        used,
        time.perf_counter() - t0,
        history,
        np.concatenate(failing) if failing else np.zeros((0, u.shape[1])),
    )


def cmaes_search(
    problem: MarginProblem,
    starts: np.ndarray,
    budget: int,
    sigma: float = 0.3,
    seed: int = 0,
    stop_at_failure: bool = True,
) -> SearchResult:
    """CMA-ES on the free variates (others held at the first start's values), population
    ``max(4, len(starts))``, mean at the first start, bounds [0, 1], at most ``budget``
    simulations."""
    from cmaes import CMA

    t0 = time.perf_counter()
    starts = np.clip(np.asarray(starts, dtype=np.float64), 0.0, 1.0)
    free = problem.free
    base = starts[0].copy()
    k = int(free.sum())
    pop = max(4, starts.shape[0])  # CMA-ES's weights are undefined below 4
    cma = CMA(
        mean=base[free].copy(),
        sigma=sigma,
        bounds=np.tile([0.0, 1.0], (k, 1)),
        seed=seed,
        population_size=pop,
    )
    used, best_u, best, first, history, failing = 0, base, -np.inf, None, [], []
    while used + pop <= budget:
        xs = np.stack([cma.ask() for _ in range(pop)])
        u = np.repeat(base[None], pop, axis=0)
        u[:, free] = xs
        margin = problem.margin(u)
        used += pop
        i = int(np.argmax(margin))
        if margin[i] > best:
            best, best_u = float(margin[i]), u[i].copy()
        history.append((used, best))
        if np.any(margin > 0):
            failing.append(u[margin > 0])
            if first is None:
                first = used
            if stop_at_failure:
                break
        cma.tell([(x, -float(m)) for x, m in zip(xs, margin, strict=True)])  # minimises
    return SearchResult(
        "cmaes",
        best_u,
        best,
        first,
        used,
        time.perf_counter() - t0,
        history,
        np.concatenate(failing) if failing else np.zeros((0, starts.shape[1])),
    )


def most_likely_failure(
    problem: MarginProblem, failing_u: np.ndarray, n_grid: int = 8, n_bisect: int = 4
) -> tuple[np.ndarray, float, int]:
    """(variates, |z| of the free variates, simulations) of the failing point nearest the
    nominal point along the ray to ``failing_u`` in standard-normal space (module docstring);
    the discrete and fixed variates keep ``failing_u``'s values."""
    free = problem.free
    z_f = to_normal(failing_u)

    def at(t):
        z = np.where(free, np.asarray(t)[:, None] * z_f[None], z_f[None])
        return to_unit(z)

    ts = np.linspace(0.0, 1.0, n_grid + 1)[1:]
    m = problem.margin(at(ts))
    used = n_grid
    fail = np.nonzero(m > 0)[0]
    if not len(fail):
        return np.asarray(failing_u), float(np.linalg.norm(z_f[free])), used
    hi = ts[fail[0]]
    lo = ts[fail[0] - 1] if fail[0] > 0 else 0.0
    for _ in range(n_bisect):
        mids = np.linspace(lo, hi, 5)[1:-1]
        m = problem.margin(at(mids))
        used += len(mids)
        f = np.nonzero(m > 0)[0]
        if len(f):
            hi = mids[f[0]]
            lo = mids[f[0] - 1] if f[0] > 0 else lo
        else:
            lo = mids[-1]
    u = at(np.array([hi]))[0]
    return u, float(hi * np.linalg.norm(z_f[free])), used


def design_point(
    problem: MarginProblem,
    mask: np.ndarray,
    iterations: int = 8,
    z0: np.ndarray | None = None,
    max_norm: float = 8.0,
) -> tuple[np.ndarray, list]:
    """The most likely failure by the HL-RF iteration (Hasofer-Lind, Rackwitz-Fiessler) in
    standard-normal space: ``z <- (grad g . z - g) grad g / |grad g|^2`` for the smooth margin
    g(z) (> 0 = failure) on the variates of ``mask`` (the others at the nominal z = 0, u = 1/2,
    or at ``z0``), one gradient simulation per iteration; the step is capped at ``max_norm``.
    Returns (z (D,), history of (|z|, exact margin)): the failing iterate nearest the origin,
    else the last one. Convergence is not guaranteed for a margin as non-linear as divergence
    (the iterates can oscillate); the point is used as an importance-sampling centre, which
    keeps the estimate unbiased whatever it is (but not efficient)."""
    mask = np.asarray(mask, dtype=bool)
    z = np.zeros(problem.dimension) if z0 is None else np.array(z0, dtype=np.float64)
    history = []
    best, best_norm = None, np.inf
    for _ in range(iterations):
        u = to_unit(z)
        value, grad_u, exact = problem.value_and_grad(u[None])
        grad = np.where(mask, grad_u[0] * stats.norm.pdf(z), 0.0)  # du/dz = phi(z)
        norm = float(np.linalg.norm(z[mask]))
        history.append((norm, float(exact[0])))
        if exact[0] > 0 and norm < best_norm:
            best, best_norm = z.copy(), norm
        gg = float(grad @ grad)
        if not np.isfinite(gg) or gg == 0.0:
            break
        new = np.where(mask, (float(grad @ z) - float(value[0])) / gg * grad, z)
        step = new - z
        n = np.linalg.norm(step)
        if n > max_norm:
            new = z + step * (max_norm / n)
        z = new
    return (z if best is None else best), history


Z_BOUND = 5.2
"""|z| bound of the design-point search (= `to_normal`'s clipping of u into [1e-7, 1 - 1e-7])."""


@dataclass
class DesignPoint:
    """Outcome of `design_point_search`.

    Attributes:
        u: variates of the design point (D,) (the discrete and fixed ones as at the start);
            z: its standard-normal coordinates (D,); free: the variates searched (D,) bool.
        distance: |z| over the free variates; start_distance: that of the start point.
        margin: the exact failure margin at ``u`` from a forward solve (`MarginProblem.margin`;
            > 0: fails).
        gradient_simulations: simulations with their gradient used by the search;
            simulations: forward solves of the re-check.
        iterations: SLSQP iterations; message: SLSQP's (or the budget's) stop reason.
        history: (gradient simulations so far, |z| of the free variates, smooth margin, exact
            margin) of every point the search evaluated.
    """

    u: np.ndarray
    z: np.ndarray
    free: np.ndarray
    distance: float
    start_distance: float
    margin: float
    gradient_simulations: int
    simulations: int
    iterations: int
    message: str
    history: list = field(default_factory=list)

    def to_dict(self, names=None, top: int = 10) -> dict:
        """JSON-ready summary, with the ``top`` free variates of largest |z| (named by
        ``names``)."""
        order = np.argsort(-np.where(self.free, np.abs(self.z), -1.0))[: min(top, self.free.sum())]
        return {
            "start_distance": self.start_distance,
            "distance": self.distance,
            "margin": self.margin,
            "gradient_simulations": self.gradient_simulations,
            "simulations": self.simulations,
            "iterations": self.iterations,
            "message": self.message,
            "top_variates": [
                {
                    "name": str(i) if names is None else names[i],
                    "z": float(self.z[i]),
                    "u": float(self.u[i]),
                }
                for i in order
            ],
            "history": self.history,
        }


class _BudgetSpent(Exception):
    pass


def design_point_search(
    problem,
    u_start: np.ndarray,
    budget: int = 16,
    level: float = 0.0,
    recheck: int = 4,
) -> DesignPoint:
    """The most likely failure (design point) near a failing case ``u_start`` (D,).

    Minimises ``|z_free|^2 / 2`` in standard-normal space (z = Phi^-1(u), the free variates of
    ``problem``, each in [-Z_BOUND, Z_BOUND]; the discrete and fixed ones stay at
    ``u_start``'s values) subject to ``smooth margin(z) >= level`` with SciPy's SLSQP (the
    margin's gradient from `MarginProblem.value_and_grad`, chained through du/dz = phi(z)), at
    most ``budget`` gradient simulations. Every evaluated point whose exact margin (from the
    same solve) is > 0 is a candidate; the ``recheck`` nearest candidates and the start are
    solved again forward (`MarginProblem.margin`) and the nearest one that fails there is
    returned. The result therefore fails whenever the start does (it is the start at worst).

    ``problem`` needs ``free`` (D,) bool, ``value_and_grad(u (n, D)) -> (smooth (n,), d
    smooth / du (n, D), exact (n,))`` and ``margin(u (n, D)) -> (n,)``.
    """
    if budget < 1:
        raise ValueError(f"budget must be >= 1 gradient simulation, got {budget}.")
    free = np.asarray(problem.free, dtype=bool)
    z0 = to_normal(np.asarray(u_start, dtype=np.float64))
    start_distance = float(np.linalg.norm(z0[free]))
    cache: dict[bytes, tuple[float, np.ndarray]] = {}
    history: list = []
    candidates: list[tuple[float, np.ndarray]] = []

    def full(x):
        z = z0.copy()
        z[free] = x
        return z

    def evaluate(x):
        key = np.asarray(x, dtype=np.float64).tobytes()
        if key not in cache:
            if len(history) >= budget:
                raise _BudgetSpent
            z = full(x)
            value, grad_u, exact = problem.value_and_grad(to_unit(z)[None])
            grad = grad_u[0] * stats.norm.pdf(z)  # du/dz = phi(z)
            distance = float(np.linalg.norm(x))
            history.append((len(history) + 1, distance, float(value[0]), float(exact[0])))
            if exact[0] > 0:
                candidates.append((distance, np.array(x, dtype=np.float64)))
            cache[key] = (float(value[0]) - level, np.asarray(grad[free], dtype=np.float64))
        return cache[key]

    x0 = np.clip(z0[free], -Z_BOUND, Z_BOUND)
    iterations, message = [0], ""
    if not free.any():
        budget, message = 0, "no free variates"

    def count(_):
        iterations[0] += 1

    try:
        if not budget:
            raise _BudgetSpent
        res = optimize.minimize(
            lambda x: 0.5 * float(x @ x),
            x0,
            jac=lambda x: np.asarray(x, dtype=np.float64),
            method="SLSQP",
            bounds=[(-Z_BOUND, Z_BOUND)] * int(free.sum()),
            constraints=[
                {
                    "type": "ineq",
                    "fun": lambda x: evaluate(x)[0],
                    "jac": lambda x: evaluate(x)[1],
                }
            ],
            options={"maxiter": budget, "ftol": 1e-6},
            callback=count,
        )
        message = str(res.message)
    except _BudgetSpent:
        message = message or f"gradient simulation budget ({budget}) spent"
    candidates.sort(key=lambda c: c[0])
    pick = [full(x) for _, x in candidates[:recheck]] + [z0]
    margins = np.asarray(problem.margin(to_unit(np.stack(pick))))
    ok = np.nonzero(margins > 0)[0]
    i = int(ok[0]) if len(ok) else len(pick) - 1  # the start when nothing re-checks
    z = pick[i]
    return DesignPoint(
        u=to_unit(z),
        z=z,
        free=free,
        distance=float(np.linalg.norm(z[free])),
        start_distance=start_distance,
        margin=float(margins[i]),
        gradient_simulations=len(history),
        simulations=len(pick),
        iterations=iterations[0],
        message=message,
        history=history,
    )

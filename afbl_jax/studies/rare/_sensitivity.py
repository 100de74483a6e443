"""Global sensitivities of a function of the standard variates u in [0, 1]^D (uniform).

- `dgsm`: derivative-based global sensitivity measures (Sobol' and Kucherenko 2009):
  nu_i = E[(df/du_i)^2] over uniform u, from batched gradients; for uniform inputs the total
  Sobol index is bounded by ``S_T,i <= nu_i / (pi^2 V)`` (V the variance of f), the bound
  returned beside nu. Grouped: the sum over a group's variates (a bound of the group's total
  index as well, by the same argument on the group's gradient).
- `sobol_indices`: variance-based first-order and total Sobol indices from SALib (Saltelli
  sampling, Jansen / Saltelli estimators), per group of variates (SALib ``groups``), with
  SALib's bootstrap confidence intervals; `sobol_indices_outputs` gives several outputs from
  the same simulations.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def dgsm(grads: np.ndarray, values: np.ndarray, groups=None) -> dict:
    """DGSM from gradients (n, D) and function values (n,) at uniform samples of [0, 1]^D.

    Returns ``{"names", "nu", "bound"}`` per group (``groups``: the group name of each
    variate; None: every variate its own group); bound = nu / (pi^2 Var f)."""
    grads = np.asarray(grads, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    ok = np.all(np.isfinite(grads), axis=1) & np.isfinite(values)
    grads, values = grads[ok], values[ok]
    nu = np.mean(grads**2, axis=0)
    names = list(range(grads.shape[1])) if groups is None else list(groups)
    order = list(dict.fromkeys(names))
    nu_g = np.array([nu[[n == g for n in names]].sum() for g in order])
    var = float(np.var(values))
    bound = nu_g / (np.pi**2 * var) if var > 0 else np.full_like(nu_g, np.nan)
    return {"names": [str(g) for g in order], "nu": nu_g, "bound": bound, "n": int(ok.sum())}


def sobol_indices(
    f: Callable[[np.ndarray], np.ndarray],
    dimension: int,
    n_base: int,
    seed: int = 0,
    groups=None,
) -> dict:
    """First-order (S1) and total (ST) Sobol indices of ``f: (n, D) -> (n,)`` on [0, 1]^D
    from SALib with ``n_base`` base samples (a power of 2; n_base (G + 2) evaluations for G
    groups, or n_base (D + 2) without groups: first-order and total indices only). Returns
    names, S1, S1_conf, ST, ST_conf (the half-widths of SALib's 95 % bootstrap intervals), the
    evaluations used and the mean and variance of f over them."""
    return sobol_indices_outputs(lambda x: {"f": f(x)}, dimension, n_base, seed, groups)["f"]


def sobol_indices_outputs(
    f: Callable[[np.ndarray], dict],
    dimension: int,
    n_base: int,
    seed: int = 0,
    groups=None,
) -> dict:
    """`sobol_indices` of several outputs from the same samples: ``f: (n, D) -> {name: (n,)}``
    is called once on the whole Saltelli sample; returns ``{name: result}`` (NaN indices for an
    output that is constant over the sample)."""
    from SALib.analyze import sobol as sobol_analyze
    from SALib.sample import sobol as sobol_sample

    names = [f"x{i}" for i in range(dimension)]
    problem = {"num_vars": dimension, "names": names, "bounds": [[0.0, 1.0]] * dimension}
    if groups is not None:
        problem["groups"] = [str(g) for g in groups]
    x = sobol_sample.sample(problem, n_base, calc_second_order=False, seed=seed)
    ys = f(x)
    out_names = list(dict.fromkeys(problem.get("groups", names)))
    out = {}
    for key, y in ys.items():
        y = np.asarray(y, dtype=np.float64)
        if np.var(y) > 0:
            res = sobol_analyze.analyze(problem, y, calc_second_order=False, seed=seed)
        else:  # a constant output (e.g. no failure among the samples): no indices
            nan = np.full(len(out_names), np.nan)
            res = {"S1": nan, "S1_conf": nan, "ST": nan, "ST_conf": nan}
        out[key] = {
            "names": out_names,
            "S1": np.asarray(res["S1"]),
            "S1_conf": np.asarray(res["S1_conf"]),
            "ST": np.asarray(res["ST"]),
            "ST_conf": np.asarray(res["ST_conf"]),
            "evaluations": int(x.shape[0]),
            "mean": float(np.mean(y)),
            "variance": float(np.var(y)),
        }
    return out

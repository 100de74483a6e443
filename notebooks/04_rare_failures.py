# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#       jupytext_version: 1.19.6
#   kernelspec:
#     display_name: Python 3 (ipykernel)
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Rare failures: the failure margin, worst cases by gradient, rare-event probabilities
#
# A Monte-Carlo study says "0 failures in 4096 cases"; a safety case needs 1e-4 .. 1e-6, the
# failing cases themselves and what drives them. Three tools, all over the same case
# distribution:
#
# 1. the **failure margin**, > 0 exactly when a run failed, and its smooth variant whose
#    gradient with respect to every uncertain input comes from the differentiable simulation;
# 2. **worst-case search** (`afbl falsify`): projected multi-start gradient ascent on the
#    margin against CMA-ES;
# 3. **rare-event probabilities** (`afbl montecarlo --estimator subset|ce-mixture|ce|is`): subset
#    simulation, and importance sampling with a cross-entropy-fitted proposal; and
#    **sensitivities** (DGSM, Sobol).
#
# Small sizes here (4 s runs) so the tests can execute the notebook.

# %%
import jax

jax.config.update("jax_enable_x64", True)

import numpy as np

import afbl_jax as A
from afbl_jax.studies import montecarlo as mc
from afbl_jax.studies import rare

dist = mc.Distribution.from_dict(
    {
        "time": {"t1": 2.0},
        "pulses": {"start": [0.5, 1.5]},
        "gust": {"start": [0.5, 1.5]},
        "turbulence": {"n_frequencies": 4},
    }
)

# %% [markdown]
# ## Cases are points of the unit cube of standard variates
# Every input is uniform on its range, so the distribution is the uniform one on [0, 1]^D;
# `cases_from_variates(draw_variates(seed))` is `sample_cases(seed)` bit for bit.

# %%
u = mc.draw_variates(dist, 8, 0)
print(u.shape, "variates;", int(mc.discrete_variates(dist).sum()), "discrete")
a, b = mc.sample_cases(dist, 8, 0), mc.cases_from_variates(dist, u)
print(
    "identical:",
    all(
        np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True)
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    ),
)

# %% [markdown]
# ## The failure margin
# max(peak attitude error / 1.2 rad, peak altitude error / 10 m) - 1 from the peaks every
# solve path computes; its sign is the simulated failure (status not ok). A case outside the
# flight envelope (status outside_envelope) is never a controller failure: the rare-event
# tools use min(failure margin, envelope margin), > 0 only for a flyable case that failed.

# %%
cols = mc.run_chunk(A.AFBL(), mc.sample_cases(dist, 32, 0))
flyable = cols["status"] != A.sim.STATUS_OUTSIDE_ENVELOPE
same = np.array_equal(cols["failure_margin"][flyable] > 0, cols["status"][flyable] != 0)
print("margin > 0 == failed (flyable cases):", same)
print("flyable:", int(flyable.sum()), "of 32; failures:", int(np.sum(cols["status"][flyable] != 0)))

# %% [markdown]
# ## Worst cases with a tighter failure limit (0.3 rad attitude error)
# Gradient ascent (4 starts) and CMA-ES (population 4) with the same budget of 8 simulations,
# solved to tight tolerances (rtol 1e-8) with 51 peak samples per run.

# %%
problem = rare.MarginProblem(A.AFBL(), dist, attitude_limit=0.3, rtol=1e-8, atol=1e-10, n_save=51)
starts = np.asarray(mc.draw_variates(dist, 4, 1))
g = rare.gradient_ascent(problem, starts, 8, learning_rate=0.1)
c = rare.cmaes_search(problem, starts, 8, seed=0)
for r in (g, c):
    print(f"{r.method:8s} best margin {r.best_margin:+.3f}, first failure after {r.first_failure}")

# %% [markdown]
# `afbl falsify --design-budget N` then searches the **most likely failure** (the design point:
# the failing point nearest the nominal one in standard-normal space) by SLSQP on the smooth
# margin, started from the worst failing case, and re-checks that the point found fails.

# %% [markdown]
# ## Rare-event probability on a toy problem with a known answer
# g(z) = a . z - 4 in 8 dimensions: P = 1 - Phi(4) = 3.2e-5. Crude Monte-Carlo would need
# ~3e6 samples for a 10 % coefficient of variation.

# %%
d = 8
a_vec = np.ones(d) / np.sqrt(d)
est = rare.cross_entropy(lambda z: z @ a_vec - 4.0, d, 500, 1000, np.random.default_rng(0))
print(f"CE: {est.probability:.3e} (cv {est.cv:.3f}, 95 % {est.ci95}), {est.simulations} sims")
print(f"exact: {rare.normal_tail(4.0):.3e}")

# %% [markdown]
# Subset simulation reaches the same probability through levels of the margin, each conditional
# probability ~0.1, with Markov chains (adaptive conditional sampling) that move every variate:
# on the closed loop that includes the turbulence phases, which no proposal over a few
# variates reaches.

# %%
est = rare.subset_simulation(lambda z: z @ a_vec - 4.0, d, 1000, np.random.default_rng(0))
print(f"subset: {est.probability:.3e} (cv {est.cv:.3f}, 95 % {est.ci95}), {est.simulations} sims")
for level in est.stages:
    print({k: round(v, 4) if isinstance(v, float) else v for k, v in level.items()})

# %% [markdown]
# ## Sensitivities
# DGSM (mean squared gradient) and Sobol indices (SALib) recover the ranking of a known function.

# %%
coef = np.array([0.5, 4.0, 0.0, 2.0])
s = rare.sobol_indices(lambda x: x @ coef, 4, 256)
print("total Sobol indices:", np.round(s["ST"], 3))

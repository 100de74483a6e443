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
# # Gain tuning through the batched simulation: L-BFGS, Adam and CMA-ES on realistic vehicles
#
# `afbl_jax.studies.tuning` tunes the AFBL gains (γ, K, λ per channel) or the FBL+PID gains
# (P, I, D). The objective is evaluated on the batched fast path (`afbl_jax.simulate_batch`,
# ensembles of 4 cases, `diffrax.diffeqsolve`, differentiable) on realistic vehicles: rigid-body
# plant, motor lag 20–50 ms, digital control 200–500 Hz with 0–1 sample delay (sensor noise off
# while training, on in the held-out evaluation). This notebook runs every piece at a small
# size (4 short cases); the studies behind the README's numbers are one command each:
#
# ```
# afbl tune --controller afbl --cases 8 --time-budget 150 --out results/tune_afbl
# afbl tune-compare --study optimizers --cases 8 --time-budget 150 --seeds 0 1 2 --out ...
# afbl tune-compare --study controllers --method cmaes --cases 8 --time-budget 150 \
#     --seeds 0 1 2 --out ...
# afbl tune-compare --study gradient-cost --cases 16 --out ...
# ```
#
# 1. cases and the normalised objective with limits;
# 2. its gradient through the scan of digital-control interval solves, against a central
#    difference;
# 3. L-BFGS, Adam, CMA-ES and CMA-ES then L-BFGS on the same cases;
# 4. the comparison studies' results (result files of the commands above, in `docs/results/`).

# %%
import json
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")  # silence XLA's C++ compile chatter

import jax

jax.config.update("jax_enable_x64", True)

import dataclasses

import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

from afbl_jax.studies import montecarlo as MC
from afbl_jax.studies import tuning as T

T_START = time.perf_counter()
np.set_printoptions(precision=4, linewidth=100)
DOCS = Path(T.__file__).resolve().parents[3] / "docs"  # the repository's docs/

# %% [markdown]
# ## 1. Cases and the objective
#
# The default tuning distribution is the Monte-Carlo default (payload, model errors, pulses,
# gusts, mean wind, Dryden turbulence, rotor drag; position hold from a trimmed start) plus
# `T.TUNING_UNMODELED`. To keep this notebook short, the runs here are 1.5 s long with
# 200–250 Hz control.

# %%
print(T.TUNING_UNMODELED)
short = MC.Distribution.from_dict(
    {
        "unmodeled": {**T.TUNING_UNMODELED, "control_rate": [200.0, 250.0]},
        "pulses": {"start": [0.3, 1.2], "duration": [0.1, 0.4]},
        "gust": {"start": [0.3, 1.2], "buildup_time": [0.2, 0.5]},
        "time": {"t1": 1.5},
    },
    "notebook",
)
cases = T.training_cases(4, seed=3, distribution=short, noise=False)
print("motor tau [s]", np.asarray(cases.unmodeled.motor_tau))
print("control rate [Hz]", np.asarray(cases.unmodeled.control_rate), "(one per group of 4)")

# %% [markdown]
# Each term is divided by its mean at the paper's gains on the same cases, so the objective at
# the paper's gains is w_att + w_alt = 2 (no failures, no limit violated); limits (mean effort
# ≤ the paper's, saturation ≤ the paper's) are smooth quadratic penalties; a failed case adds
# w_div (1 + unsimulated fraction).

# %%
# tight solver tolerances: the central difference in section 2 then checks the gradient closely
objective = T.ObjectiveConfig(rtol=1e-8, atol=1e-10)
config = T.TuneConfig(
    controller="afbl",
    objective=objective,
    n_cases=4,
    steps=4,
    checkpoint_every=0,
    population=8,
    sigma=0.1,
)
tuner = T.Tuner(config, cases=cases)
z0 = tuner.space.init_z()  # the paper's gains: the box centre
loss0, costs0 = tuner.loss_and_costs(z0)
print("objective at the paper's gains:", float(loss0))
for name in ("ise_attitude", "ise_altitude", "effort", "saturation", "failed"):
    print(f"{name:13s}", np.asarray(getattr(costs0, name)))

# %% [markdown]
# ## 2. The gradient
#
# `jax.value_and_grad` through `simulate_batch(strategy="ensemble")`: a `lax.scan` over the
# control samples with one `diffeqsolve` per interval (`RecursiveCheckpointAdjoint`). A
# directional central difference checks it.

# %%
z1 = {k: 0.1 * jnp.sin(jnp.arange(4.0) + 3 * i) for i, k in enumerate(tuner.space.names)}
(value, _), grad = tuner.value_and_grad(z1)
d = {k: jnp.cos(jnp.arange(4.0) + i) for i, k in enumerate(tuner.space.names)}
h = 1e-4
f = [float(tuner.loss_and_costs({k: z1[k] + s * d[k] for k in z1})[0]) for s in (h, -h)]
print("directional derivative: autodiff", sum(float(jnp.dot(grad[k], d[k])) for k in d))
print("                   central diff.", (f[0] - f[1]) / (2 * h))

# %% [markdown]
# ## 3. Four optimisers on the same cases
#
# L-BFGS (optax, backtracking Armijo line search; the default), Adam, CMA-ES (the `cmaes`
# package, the whole population in one batched call) and the hybrid (here two CMA-ES
# generations, then L-BFGS from the best candidate). Each history row holds the objective after
# an iteration and the wall time since the start (compilation excluded, timed separately).

# %%
runs = {}
for method in ("lbfgs", "adam", "cmaes", "hybrid"):
    t = T.Tuner(dataclasses.replace(config, method=method, cmaes_generations=2), cases=cases)
    r = t.run(progress=False, log=lambda *a: None)
    runs[method] = {0: r.history}
    print(f"{method:6s} objective {r.initial_loss:.4f} -> {r.final_loss:.4f}")
from afbl_jax.plotting.tuning import plot_loss_vs_time

small_fig = Path(tempfile.mkdtemp()) / "loss_vs_time_small.png"
plot_loss_vs_time(runs, small_fig, title="4 short cases, 4 iterations")
plt.imshow(plt.imread(small_fig))
plt.axis("off")

# %% [markdown]
# ## 4. The comparison studies
#
# The documentation's gain-tuning page shows these results as tables; the files are the
# commands' outputs with their provenance (command, revision, machine, date), kept in
# `docs/results/`.

# %%
for name in ("tuning_gradient_cost.json", "tuning_optimizers.json", "tuning_controllers.json"):
    path = DOCS / "results" / name
    if not path.exists():
        print(f"{path}: not present")
        continue
    doc = json.loads(path.read_text())
    print(name, "--", doc["provenance"]["command"])
    (result,) = doc["files"].values()
    if name == "tuning_controllers.json":
        print(T.format_controllers(result["heldout"]))
        continue
    result = {k: v for k, v in result.items() if k not in ("meta", "runs")}
    print(json.dumps(result, indent=1)[:2500])
fig_path = DOCS / "figures" / "tuning_loss_vs_time.png"
if fig_path.exists():
    plt.figure(figsize=(8, 5))
    plt.imshow(plt.imread(fig_path))
    plt.axis("off")
print(f"notebook ran in {time.perf_counter() - T_START:.0f} s")

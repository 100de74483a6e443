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
# # Monte-Carlo robustness: FBL + PID vs adaptive FBL over payload, model error and wind
#
# Four canonical runs say little about robustness. Here every case draws a payload, model
# errors (inertia, thrust and rotor-drag coefficients, a thrust-to-weight limit of 2.5), the
# paper's disturbance pulses, a steady mean wind up to 8 m/s, a 1-cosine gust and the Dryden
# turbulence of that wind (MIL-F-8785C / MIL-HDBK-1797 low altitude) acting through the
# rotor-drag aerodynamic model, and a mission. The vehicle flies as real multirotors do: an
# outer position loop holds or steers its position around the paper's inner loops, from a
# start in equilibrium with the wind (a trim). A case outside the vehicle's flight envelope is
# named as such before it is simulated. Both controllers fly the *same* case (paired
# comparison).
#
# The notebook runs a small batch (so the tests can execute it); the full study is
# `afbl montecarlo --cases 4096 --controllers fbl,afbl --seed 0 --out results/mc`.

# %%
import jax

jax.config.update("jax_enable_x64", True)

import numpy as np

import afbl_jax as A
from afbl_jax.io import table_columns
from afbl_jax.plotting.montecarlo import figure_ecdf
from afbl_jax.studies import montecarlo as mc

# %% [markdown]
# ## The distribution
# Written once (`DEFAULT_DISTRIBUTION`), overridable from a TOML/JSON file.

# %%
dist = mc.default_distribution()
print(dist.describe())

# %% [markdown]
# ## Sampling: case i depends only on (seed, i)

# %%
cases = mc.sample_cases(dist, 8, seed=0)
print(
    {
        k: np.round(np.asarray(v)[:4], 3)
        for k, v in cases.inputs.items()
        if k
        in ("payload_fraction", "mean_wind_speed", "gust_speed", "trim_tilt", "envelope_margin")
    }
)
again = mc.sample_cases(dist, 8, seed=0, start=4)
assert np.array_equal(cases.inputs["gust_speed"][4:], again.inputs["gust_speed"][:4])

# %% [markdown]
# ## The wind one case feels

# %%
import matplotlib.pyplot as plt

scenario, vehicle, model = cases.case(0)
ts = np.linspace(0.0, 20.0, 801)
w = np.asarray(jax.vmap(scenario.wind)(ts))
fig, ax = plt.subplots(figsize=(8, 2.8))
ax.plot(ts, w, label=["x", "y", "z"])
ax.set_xlabel("t [s]")
ax.set_ylabel("wind [m/s]")
ax.legend()
plt.show()

# %% [markdown]
# ## The trimmed start and the position loop
# Case 0 flown by AFBL with the position loop: it starts tilted into the wind (the trim), and
# the loop holds the position against the gust and the turbulence.

# %%
r = A.simulate(
    A.AFBL(),
    scenario,
    vehicle,
    model,
    aerodynamics=cases.aerodynamics,
    position_loop=cases.position_loop,
    n_save=401,
)
fig, axes = plt.subplots(1, 2, figsize=(10, 3), layout="constrained")
axes[0].plot(r.ts, r.plant[:, 3:5], label=["phi", "theta"])
axes[0].plot(r.ts, r.reference[:, :2], "k--", lw=0.8, label=["commanded", None])
axes[0].set_xlabel("t [s]")
axes[0].set_ylabel("attitude [rad]")
axes[0].legend(fontsize=8)
axes[1].plot(r.ts, r.plant[:, 0:3], label=["x", "y", "z"])
axes[1].set_xlabel("t [s]")
axes[1].set_ylabel("position [m]")
axes[1].legend(fontsize=8)
plt.show()
print(
    "trim tilt [rad]:",
    float(cases.inputs["trim_tilt"][0]),
    "ISE position [m^2 s]:",
    float(r.ise_position),
)

# %% [markdown]
# ## A paired batch
# 8 cases in one chunk, both controllers; the metrics and sampled inputs become one table.

# %%
controllers = {"fbl": A.make_controller("fbl"), "afbl": A.make_controller("afbl")}
table = mc.run_montecarlo(controllers, dist, 8, seed=0, chunk_size=8, progress=False)
cols = table_columns(table)
summary = mc.summarize(cols)
print(mc.format_summary(summary))

# %%
fig = figure_ecdf(cols)
plt.show()

# %% [markdown]
# With 8 cases the intervals are wide; the 4096-case study in the README narrows them.

"""Names of the rows of `afbl_jax.studies.bench` and its default batch sizes, in a module that
imports nothing (so ``afbl bench --help`` lists them without starting JAX). What each row
measures is described in `afbl_jax.studies.bench`."""

DEFAULT_SIZES = (64, 1024, 4096, 16384)
"""Batch sizes of ``afbl bench`` by default."""

LOOP_STRATEGIES = ("scipy_rk45_loop", "diffrax_loop")
"""Rows that solve one case after the other (the canonical case)."""

BATCH_ROWS = (
    "vmap",
    "ensemble",
    "ensemble_f32",
    "ensemble_f32_chunked",
    "montecarlo_default",
    "montecarlo_default_1dev",
    "montecarlo_default_no_queue",
    "montecarlo_default_diffeqsolve",
    "montecarlo_default_unmodeled",
    "montecarlo_default_unmodeled_diffeqsolve",
)
"""Rows of one `simulate_batch` setting each on the canonical case (`bench.BATCH_STRATEGIES`)."""

MONTECARLO_CASE_ROWS = ("montecarlo_cases", "montecarlo_cases_no_position_loop")
"""Rows on the Monte-Carlo default distribution's own cases (AFBL, ``afbl montecarlo``'s default
strategy): the default (position hold, trimmed start) and the same cases (the same wind,
turbulence realisation included) flown without the position loop from rest
(`without_position_loop`)."""

MONTECARLO_SCIPY_ROW = "scipy_rk45_montecarlo_cases"
"""The scipy baseline on the Monte-Carlo default distribution's own cases (`solve_ivp` with the
NumPy closed loop of `afbl_jax.studies.numpy_loop`): the ratio of `MONTECARLO_CASE_ROWS`."""

GRADIENT_ROW = "tuning_gradient"
"""The gain-tuning objective's value-and-gradient against its forward pass on the same training
cases (`afbl_jax.studies.tuning.gradient_cost`), one row per precision."""

ALL_STRATEGIES = (
    *LOOP_STRATEGIES,
    *BATCH_ROWS,
    MONTECARLO_SCIPY_ROW,
    *MONTECARLO_CASE_ROWS,
    GRADIENT_ROW,
)
"""Every row, in the order they are measured."""

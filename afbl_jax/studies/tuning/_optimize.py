"""The tuning loop: L-BFGS (default), Adam, CMA-ES or CMA-ES then L-BFGS over the unconstrained
gain vector z (`GainSpace.log_gains`), a wall-time budget, checkpoints and exact resume.

- ``lbfgs``: `optax.lbfgs` with a backtracking Armijo line search
  (`optax.scale_by_backtracking_linesearch`: sufficient decrease f(z + a d) <= f(z) +
  1e-4 a g.d, the step a times `LS_DECREASE` after each rejected trial, at most
  ``linesearch_steps`` trials) on the fixed training set. When no trial decreases enough the
  iterate stays (the objective never goes up), the curvature memory is dropped (the next
  direction is steepest descent: a direction from a poor memory need not descend) and the
  next search starts below the last trial step; after an accepted step the next search starts
  at the quasi-Newton step a = 1. A trial is a forward evaluation of the
  objective; after the step one value-and-gradient at the new point serves as the next
  iteration's start, so an iteration costs at most ``linesearch_steps`` + 1 forward passes,
  one of them with its gradient (recorded per iteration as ``evaluations``).
- ``adam``: `optax.adam` with a cosine or constant schedule, global-norm clipping and
  `optax.zero_nans`.
- ``cmaes``: `cmaes.CMA` (the ``cmaes`` package), the whole population evaluated in ONE
  `afbl_jax.simulate_batch` call (controllers batched over candidates x cases); the current
  gains are the best candidate seen so far. With a `DaskExecutor` (``Tuner(executor=...)``)
  the population is split into consecutive groups of candidates, one task each on the
  cluster's workers (as many groups as task slots; a group boundary never splits an ensemble
  group of cases), the same numbers as the one call.
- ``hybrid``: ``cmaes_generations`` CMA-ES generations (global search), then L-BFGS as above
  from the best candidate seen (local refinement, a fresh curvature memory).

Every method stops after ``steps`` iterations (generations for CMA-ES) or at the time budget
(`Tuner.run`: counted after compiling one iteration, or from a given start with compilation
included and an unfinished iteration abandoned at the deadline); the clock continues across a
resume. The history has
one row per iteration: the objective at the gains held after it, the wall time, the gains.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import json
import math
import pickle
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from ...model import AbstractController
from ..executors import Executor, LocalExecutor
from ..montecarlo import GROUP_SIZE
from ._cases import DEFAULT_THRUST_TO_WEIGHT
from ._objective import (
    CaseCosts,
    GainSpace,
    ObjectiveConfig,
    case_costs,
    cases_for,
    objective,
    objective_of_costs,
    reference_terms,
    tile_cases,
)

METHODS = ("lbfgs", "adam", "cmaes", "hybrid")
POPULATION_METHODS = ("cmaes", "hybrid")
"""Methods that evaluate CMA-ES populations (on a cluster with a `DaskExecutor`)."""
SCHEDULES = ("cosine", "constant")
CHECKPOINT_ARRAYS = "checkpoint.eqx"
CHECKPOINT_CMA = "checkpoint_cma.pkl"
CHECKPOINT_STATE = "checkpoint.json"
CHANNELS = ("phi", "theta", "psi", "z")
LS_DECREASE = 0.3
"""Factor of the L-BFGS trial step after each rejected trial."""
LS_INCREASE = 3.0
"""Factor of optax's first trial step over the last one (at most 1, the quasi-Newton step):
after a search that found no step, the next starts at LS_INCREASE * LS_DECREASE times its last
trial; after an accepted step the next search starts at 1."""


@dataclass(frozen=True)
class TuneConfig:
    """Everything that defines a tuning run (recorded in meta.json and the checkpoint).

    Attributes:
        controller: "afbl" or "fbl".
        objective: the `ObjectiveConfig` (objective, risk, weights, limits, solver settings).
        n_cases: training cases for the robust objective (ignored for nominal: the canonical 4).
        seed: seed of the training cases (and of CMA-ES's sampling).
        steps: iterations (L-BFGS / Adam steps, CMA-ES generations).
        method: "lbfgs" (default), "adam", "cmaes" or "hybrid" (CMA-ES, then L-BFGS).
        linesearch_steps: L-BFGS: most trial steps (forward evaluations) per iteration.
        time_budget: wall-time budget [s] (None: no budget): of the iterations, or from a
            given start (`Tuner.run`'s ``started``: compilation included).
        learning_rate, schedule, clip_norm: Adam (peak step in z units; "cosine" decays to
            10 % over ``steps``).
        sigma, population: CMA-ES initial step size (z units) and population (None: the
            library's default 4 + 3 ln 12 = 11).
        lower, upper: gain box as factors of the paper's gains.
        thrust_to_weight: rotor limit (max thrust / nominal weight); None = unlimited.
        checkpoint_every: write a checkpoint every this many iterations (0: never).
        cmaes_generations: hybrid: CMA-ES generations before L-BFGS takes over.
    """

    controller: str = "afbl"
    objective: ObjectiveConfig = field(default_factory=ObjectiveConfig)
    n_cases: int = 64
    seed: int = 0
    steps: int = 100
    method: str = "lbfgs"
    linesearch_steps: int = 4
    time_budget: float | None = None
    learning_rate: float = 0.05
    schedule: str = "cosine"
    clip_norm: float = 1.0
    sigma: float = 0.2
    population: int | None = None
    lower: float = 0.1
    upper: float = 10.0
    thrust_to_weight: float | None = DEFAULT_THRUST_TO_WEIGHT
    checkpoint_every: int = 10
    cmaes_generations: int = 5

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; allowed: {', '.join(METHODS)}.")
        if self.schedule not in SCHEDULES:
            raise ValueError(
                f"unknown schedule {self.schedule!r}; allowed: {', '.join(SCHEDULES)}."
            )
        if self.cmaes_generations < 1:
            raise ValueError(f"cmaes_generations must be >= 1, got {self.cmaes_generations}.")
        if self.linesearch_steps < 1:
            raise ValueError(f"linesearch_steps must be >= 1, got {self.linesearch_steps}.")
        if self.steps < 0 or self.n_cases < 1 or self.checkpoint_every < 0:
            raise ValueError(
                "need steps >= 0, n_cases >= 1, checkpoint_every >= 0; got "
                f"{self.steps}, {self.n_cases}, {self.checkpoint_every}."
            )
        if not (self.learning_rate > 0 and self.clip_norm > 0 and self.sigma > 0):
            raise ValueError("learning_rate, clip_norm and sigma must be > 0.")
        if self.population is not None and self.population < 2:
            raise ValueError(f"population must be >= 2, got {self.population}.")
        if self.time_budget is not None and not self.time_budget > 0:
            raise ValueError(f"time_budget must be > 0 seconds, got {self.time_budget}.")
        if self.thrust_to_weight is not None and not self.thrust_to_weight > 1.0:
            raise ValueError(
                f"thrust_to_weight must be > 1 (or None), got {self.thrust_to_weight}."
            )
        self.space()  # validates controller and box

    def space(self) -> GainSpace:
        return GainSpace(self.controller, lower=self.lower, upper=self.upper)

    def objective_key(self) -> TuneConfig:
        """The fields the objective's compiled code depends on (controller, box, objective,
        rotor limit): runs differing only in seed, method or budget share one compilation."""
        return TuneConfig(
            controller=self.controller,
            objective=self.objective,
            lower=self.lower,
            upper=self.upper,
            thrust_to_weight=self.thrust_to_weight,
            n_cases=1,
            steps=0,
            checkpoint_every=0,
        )

    def step_key(self) -> TuneConfig:
        """`objective_key` plus the fields of the optax update (method, Adam's schedule)."""
        key = self.objective_key()
        if self.method in ("lbfgs", "hybrid"):
            return dataclasses.replace(key, linesearch_steps=self.linesearch_steps)
        if self.method == "adam":
            return dataclasses.replace(
                key,
                method="adam",
                steps=self.steps,
                learning_rate=self.learning_rate,
                schedule=self.schedule,
                clip_norm=self.clip_norm,
            )
        return key

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> TuneConfig:
        d = dict(d)
        d["objective"] = ObjectiveConfig(**d["objective"])
        return cls(**d)


def strongly_typed(tree):
    """``tree`` with every weakly typed array leaf (a Python scalar's type, which a jitted
    function's output loses) given its dtype for good; other leaves unchanged. A state
    passed to a jitted step keeps one abstract type from the first call on: no retracing."""
    return jax.tree.map(lambda x: jnp.asarray(x, dtype=x.dtype) if eqx.is_array(x) else x, tree)


def make_optimizer(config: TuneConfig) -> optax.GradientTransformation:
    """The optax transformation of a gradient method (L-BFGS, also the hybrid's second phase,
    or Adam with guards)."""
    if config.method in ("lbfgs", "hybrid"):
        # the trial counter starts at 0 and the loop runs while it is <= the maximum
        search = optax.scale_by_backtracking_linesearch(
            max_backtracking_steps=config.linesearch_steps - 1,
            decrease_factor=LS_DECREASE,
            increase_factor=LS_INCREASE,
        )
        return optax.lbfgs(linesearch=search)
    if config.schedule == "cosine":
        lr = optax.cosine_decay_schedule(config.learning_rate, max(config.steps, 1), alpha=0.1)
    else:
        lr = optax.constant_schedule(config.learning_rate)
    return optax.chain(
        optax.zero_nans(), optax.clip_by_global_norm(config.clip_norm), optax.adam(lr)
    )


@dataclass
class TuneResult:
    """Outcome of `tune`: final log-gains, controller, per-iteration history, config."""

    params: dict
    controller: AbstractController
    history: list[dict]
    config: TuneConfig
    reference: Any = None
    costs: Any = None
    compile_s: float = 0.0
    stopped: str | None = None

    @property
    def initial_loss(self) -> float:
        return self.history[0]["loss"]

    @property
    def final_loss(self) -> float:
        return self.history[-1]["loss"]


def _flat(z: dict, names) -> np.ndarray:
    return np.concatenate([np.asarray(z[n], dtype=float) for n in names])


def _unflat(x, names) -> dict:
    x = jnp.asarray(x)
    return {n: x[..., 4 * i : 4 * i + 4] for i, n in enumerate(names)}


class Tuner:
    """Holds the jitted objective, gradient and step functions for one `TuneConfig` (build
    once, reuse: no retracing across iterations or across `run` calls). ``executor``: where
    CMA-ES populations are evaluated during `run` (None: this process; a `DaskExecutor`:
    groups of candidates as tasks of a Dask cluster)."""

    def __init__(
        self, config: TuneConfig, cases=None, distribution=None, executor: Executor | None = None
    ):
        self.config = config
        self.executor = executor
        self.executor_record: dict | None = None  # the last run's Dask cluster (None: local)
        self._session = None
        self._start = None  # L-BFGS: (objective, gradient) at the current z
        self._estimate = None  # L-BFGS: seconds a next iteration takes at most (compiled)
        self.space = config.space()
        self.cases = (
            cases
            if cases is not None
            else cases_for(
                config.objective,
                config.n_cases,
                config.seed,
                config.thrust_to_weight,
                distribution=distribution,
            )
        )
        self.reference_costs = _costs(config.objective_key(), self.space.init_params(), self.cases)
        self.reference = reference_terms(self.reference_costs)
        self.optimizer = None if config.method == "cmaes" else make_optimizer(config)

    # -- objective in z ------------------------------------------------------------------
    def loss_and_costs(self, z: dict):
        """(objective, `CaseCosts`) at z (forward only)."""
        costs = _costs(self.config.objective_key(), self.space.log_gains(z), self.cases)
        return objective_of_costs(costs, self.reference, self.config.objective), costs

    def value_and_grad(self, z: dict):
        """((objective, CaseCosts), d objective / dz): one reverse pass over the cases, or in
        chunks spread over the local devices (`chunked_value_and_grad`)."""
        return chunked_value_and_grad(self.config.objective_key(), z, self.cases, self.reference)

    def population_losses(self, zs: np.ndarray) -> np.ndarray:
        """Objective of each row of ``zs`` (P, 12), all candidates in one batched call (during
        `run` with a Dask executor: groups of candidates, one task each)."""
        fn = functools.partial(
            population_losses, self.config.objective_key(), self.cases, self.reference
        )
        if self._session is None or self._session.record["kind"] == "local":
            return fn(zs)
        parts = population_groups(len(zs), self.cases.n_cases, self._session.slots())
        return np.concatenate(self._session.map(fn, [zs[a:b] for a, b in parts]))

    # -- state ---------------------------------------------------------------------------
    def init(self):
        self._start = None
        z = self.space.init_z()
        if self.config.method in POPULATION_METHODS:
            from cmaes import CMA

            x0 = _flat(z, self.space.names)
            cma = CMA(
                mean=x0,
                sigma=self.config.sigma,
                seed=int(self.config.seed % (2**32)),
                population_size=self.config.population,
            )
            state = {"cma": cma, "best": x0, "best_loss": math.inf}
            if self.config.method == "hybrid":
                state["lbfgs"] = None  # the L-BFGS state once CMA-ES has handed over
            return z, state
        return z, self._optimizer_init(z)

    def _optimizer_init(self, z):
        """The gradient method's initial state at z, its weakly typed leaves (optax's line
        search starts its trial counter as a Python 0) made strongly typed, as the step
        returns them: otherwise the jitted L-BFGS step, traced first with the initial state,
        would be traced and compiled a second time in the second iteration."""
        return strongly_typed(self.optimizer.init(z))

    def _row(self, step, z, loss, t, costs=None, grad_norm=math.nan, evaluations=0) -> dict:
        row = {
            "step": step,
            "time_s": float(t),
            "evaluations": int(evaluations),
            "loss": float(loss),
            "grad_norm": float(grad_norm),
        }
        for key in ("ise_attitude", "ise_altitude", "effort", "saturation"):
            row[key] = math.nan if costs is None else float(np.mean(getattr(costs, key)))
        row["failed"] = -1 if costs is None else int(np.sum(costs.failed))
        params = self.space.log_gains(z)
        for name in self.space.names:
            for ch, v in zip(CHANNELS, np.exp(np.asarray(params[name])), strict=True):
                row[f"{name}_{ch}"] = float(v)
        return row

    def _iterate(self, z, state):
        """One iteration: (new z, new state, loss at new z or None, grad norm, evaluations)."""
        cfg = self.config
        if cfg.method == "cmaes":
            return self._cma_iterate(z, state)
        if cfg.method == "hybrid":
            if state["lbfgs"] is None and state["cma"].generation < cfg.cmaes_generations:
                return self._cma_iterate(z, state)
            if state["lbfgs"] is None:  # hand over: L-BFGS from the best candidate seen
                z = _unflat(state["best"], self.space.names)
                state["lbfgs"] = self._optimizer_init(z)
                self._start = None
            z, state["lbfgs"], loss, gnorm, nev = self._lbfgs_iterate(z, state["lbfgs"])
            return z, state, loss, gnorm, nev
        if cfg.method == "lbfgs":
            return self._lbfgs_iterate(z, state)
        (value, _), grads = self.value_and_grad(z)
        z, state, gnorm = _adam_step(cfg.step_key(), z, state, grads)
        return z, state, None, float(gnorm), 1

    def _cma_iterate(self, z, state):
        """One CMA-ES generation; z: the best candidate seen so far."""
        cma = state["cma"]
        xs = np.stack([cma.ask() for _ in range(cma.population_size)])
        losses = self.population_losses(xs)
        # non-finite objectives rank last
        ranked = np.where(np.isfinite(losses), losses, np.finfo(float).max)
        cma.tell(list(zip(xs, ranked, strict=True)))
        i = int(np.argmin(ranked))
        if ranked[i] < state["best_loss"]:
            state["best"], state["best_loss"] = xs[i], float(ranked[i])
        z = _unflat(state["best"], self.space.names)
        return z, state, state["best_loss"], math.nan, len(xs)

    def _lbfgs_iterate(self, z, state):
        """One L-BFGS iteration (line search, then value and gradient at the new point)."""
        cfg = self.config
        if self._start is None:  # value and gradient at z (first iteration, resume)
            (value, _), grad = self.value_and_grad(z)
        else:
            value, grad = self._start
        new_z, new_state = _lbfgs_step(
            cfg.step_key(), z, state, value, grad, self.cases, self.reference
        )
        trials = int(optax.tree_utils.tree_get(new_state, "num_linesearch_steps"))
        gnorm = float(optax.tree_utils.tree_norm(grad))
        if not float(optax.tree_utils.tree_get(new_state, "decrease_error")) <= 0.0:
            # no trial decreased enough: stay, restart from steepest descent (the curvature
            # memory is dropped: its direction need not descend), and start the next search
            # below the last trial step
            rate = optax.tree_utils.tree_get(new_state, "learning_rate")
            state = optax.tree_utils.tree_set(
                self._optimizer_init(z), learning_rate=rate * LS_DECREASE
            )
            self._start = (value, grad)
            return z, state, float(value), gnorm, trials
        # the curvature memory scales the next direction, so its search starts at the
        # quasi-Newton step a = 1 (Nocedal & Wright, Numerical Optimization, sec. 3.5), not at
        # LS_INCREASE times the step accepted here (optax's start, made for gradient descent)
        rate = optax.tree_utils.tree_get(new_state, "learning_rate")
        new_state = optax.tree_utils.tree_set(
            new_state, learning_rate=jnp.full_like(rate, 1.0 / LS_INCREASE)
        )
        t = time.perf_counter()
        (new_value, _), new_grad = self.value_and_grad(new_z)
        jax.block_until_ready(new_grad)
        # the cost of a next iteration at most: its trials and one value-and-gradient
        self._estimate = (cfg.linesearch_steps + 1) * (time.perf_counter() - t)
        self._start = (new_value, new_grad)
        return new_z, new_state, float(new_value), gnorm, trials + 1

    def warmup(self) -> float:
        """Compile one iteration (on a copy of the initial state, discarded; the hybrid: one
        generation and one L-BFGS iteration); returns the seconds it took. `run` calls it
        before starting its clock."""
        t = time.perf_counter()
        z, state = self.init()
        z, state, *_ = self._iterate(z, copy.deepcopy(state))
        if self.config.method == "hybrid":
            self._start = None
            z, *_ = self._lbfgs_iterate(z, self._optimizer_init(z))
        jax.block_until_ready(z)
        self._start = None
        self._estimate = None
        return time.perf_counter() - t

    def run(
        self,
        out: str | Path | None = None,
        resume: bool = False,
        progress: bool = True,
        stop_after: int | None = None,
        log=print,
        started: float | None = None,
        reserve: float = 0.0,
    ) -> TuneResult:
        """Optimise for ``config.steps`` iterations or until the time budget is spent (or stop
        after ``stop_after`` iterations, for tests of resuming). Checkpoints go to ``out`` every
        ``checkpoint_every`` iterations; ``resume`` continues from ``out``'s checkpoint (same
        config required) with the same result as an uninterrupted run. History row 0 is the
        starting point (the paper's gains), row i the gains after iteration i. The executor's
        session (a Dask client) is open during the run.

        Time budget (``config.time_budget``): with ``started`` None, the clock starts after
        compiling one iteration (`warmup`) and the loop stops before an iteration that would
        end past the budget (estimated from the last one). With ``started`` (a
        `time.perf_counter` value, e.g. when the command started) the clock runs from then,
        compilation included: the loop stops once ``started + time_budget - reserve`` has
        passed or the last iteration's duration exceeds what is left, and an iteration still
        running at that deadline (the first one compiles) is abandoned. Either way the result
        holds the best point so far (``stopped`` says why it stopped early). With
        ``progress``, one line per iteration goes to ``log``."""
        executor = self.executor if self.config.method in POPULATION_METHODS else None
        with (executor or LocalExecutor()).session() as session:
            self._session = session
            self.executor_record = None if session.record["kind"] == "local" else session.record
            try:
                return self._run(out, resume, progress, stop_after, log, started, reserve)
            finally:
                self._session = None

    def _run(self, out, resume, progress, stop_after, log, started, reserve) -> TuneResult:
        cfg = self.config
        budgeted = started is not None and cfg.time_budget is not None
        if started is None:  # the clock starts after compiling one iteration
            compile_s = self.warmup() if cfg.steps > 0 else 0.0
            t_start = None
        else:  # the clock started with the command: compilation counts
            compile_s, t_start = math.nan, started
        deadline = started + cfg.time_budget - reserve if budgeted else None
        z, state = self.init()
        t_start = time.perf_counter() if t_start is None else t_start
        history: list[dict] = []
        start, offset = 0, 0.0

        def elapsed():
            return offset + time.perf_counter() - t_start

        if resume:
            if out is None:
                raise ValueError("resume needs the output folder holding the checkpoint.")
            start, z, state, history = load_checkpoint(out, cfg, z, state)
            offset = history[-1]["time_s"] if history else 0.0
            log(f"resumed from {Path(out) / CHECKPOINT_STATE} at iteration {start}")
        else:
            loss0, costs0 = self.loss_and_costs(z)
            history.append(self._row(0, z, loss0, elapsed() if budgeted else 0.0, costs0))
            if cfg.method in POPULATION_METHODS:  # the starting point is the best seen so far
                state["best_loss"] = float(loss0)
        best = (history[-1]["loss"], z, len(history) - 1)

        end = cfg.steps if stop_after is None else min(cfg.steps, start + stop_after)
        if progress and start < end:
            log(
                f"tune ({cfg.method}): {end - start} iterations"
                + (f", time budget {cfg.time_budget:g} s" if cfg.time_budget else "")
                + (" (the first one compiles)" if budgeted and start == 0 else "")
            )
        last = 0.0
        stopped, abandoned = None, False
        for it in range(start, end):
            if deadline is not None:
                left = deadline - time.perf_counter()
                if left <= 0 or (last > 0 and last > left):
                    stopped = f"stopped before iteration {it + 1}: {max(left, 0.0):.1f} s left"
                    break
            elif cfg.time_budget is not None and elapsed() + last > cfg.time_budget:
                stopped = f"stopped after {it} iterations ({elapsed():.1f} s)"
                break
            t_it = time.perf_counter()
            if deadline is None:
                outcome = self._iterate(z, state)
            else:
                outcome = within_deadline(
                    lambda z=z, state=state: self._iterate(z, state), deadline
                )
                if outcome is None:
                    stopped = f"iteration {it + 1} did not finish before the deadline"
                    abandoned = True
                    break
            z, state, loss, gnorm, nev = outcome
            costs = None
            if loss is None:
                loss, costs = self.loss_and_costs(z)
            took = time.perf_counter() - t_it
            # the estimate of the next iteration (the first one's time includes compiling)
            last = took if self._estimate is None else min(took, self._estimate)
            row = self._row(it + 1, z, loss, elapsed(), costs, gnorm, nev)
            history.append(row)
            if row["loss"] < best[0]:
                best = (row["loss"], z, it + 1)
            if not math.isfinite(row["loss"]):
                log(f"iteration {it + 1}: non-finite loss {row['loss']}")
            if progress:
                log(
                    f"iteration {it + 1}/{end}: objective {row['loss']:.5e}, "
                    f"{nev} evaluations, {took:.1f} s (total {row['time_s']:.1f} s)"
                )
            done = it + 1
            if (
                out is not None
                and cfg.checkpoint_every
                and (done % cfg.checkpoint_every == 0 or done == end)
            ):
                save_checkpoint(out, cfg, done, z, state, history)
        if stopped is not None:
            log(
                f"time budget {cfg.time_budget:g} s: {stopped}; keeping the best point so far "
                f"(iteration {best[2]}, objective {best[0]:.5e})"
            )
            # (an abandoned iteration may still change a CMA-ES state in place)
            if out is not None and cfg.checkpoint_every and len(history) > 1 and not abandoned:
                save_checkpoint(out, cfg, history[-1]["step"], z, state, history)
        z = best[1]
        params = self.space.log_gains(z)
        loss, costs = self.loss_and_costs(z)
        final = self._row(history[-1]["step"], z, loss, history[-1]["time_s"], costs)
        final["evaluations"] = history[-1]["evaluations"]
        final["grad_norm"] = history[-1]["grad_norm"]
        history[-1].update(final)
        return TuneResult(
            params,
            self.space.controller_of(params),
            history,
            cfg,
            self.reference,
            costs,
            compile_s,
            stopped,
        )


_ABANDONED: list[threading.Thread] = []


def abandoned_work() -> bool:
    """Whether a computation abandoned at a deadline (`within_deadline`) is still running: the
    process must then end with ``os._exit`` (a daemon thread inside XLA aborts the
    interpreter's normal shutdown)."""
    return any(t.is_alive() for t in _ABANDONED)


def within_deadline(fn, deadline: float):
    """``fn()`` run in a daemon thread; its result, or None when it has not finished by
    ``deadline`` (`time.perf_counter` seconds; the thread is abandoned and ends with the
    process)."""
    box: dict = {}

    def target():
        try:
            box["value"] = fn()
        except BaseException as e:  # re-raised in the caller
            box["error"] = e

    worker = threading.Thread(target=target, daemon=True)
    worker.start()
    worker.join(max(deadline - time.perf_counter(), 0.0))
    if worker.is_alive():
        _ABANDONED.append(worker)
        return None
    if "error" in box:
        raise box["error"]
    return box["value"]


def _objective_z(z, config: TuneConfig, cases, ref):
    space = config.space()
    return objective(space.log_gains(z), space, cases, config.objective, ref)


@eqx.filter_jit
def _costs(config: TuneConfig, params, cases):
    return case_costs(config.space().controller_of(params), cases, config.objective)


@eqx.filter_jit
def _value_and_grad(config: TuneConfig, z, cases, ref):
    """((objective, CaseCosts), d objective / dz) in one reverse pass; compiled once per config
    and batch shape."""
    return jax.value_and_grad(_objective_z, has_aux=True)(z, config, cases, ref)


@eqx.filter_jit
def _costs_cotangent(config: TuneConfig, costs: CaseCosts, ref):
    """(objective, d objective / d costs) at the per-case ``costs`` (the cotangent of every
    inexact leaf; None for the others)."""
    diff, static = eqx.partition(costs, eqx.is_inexact_array)

    def fn(d):
        return objective_of_costs(eqx.combine(d, static), ref, config.objective)

    return jax.value_and_grad(fn)(diff)


@eqx.filter_jit
def _chunk_grad(config: TuneConfig, z, cases, cotangent):
    """d/dz of sum_i <cotangent_i, costs_i(z)> over the cases of one chunk (a vector-Jacobian
    product of the per-case costs; entries with a zero cotangent do not enter)."""

    def fn(z):
        space = config.space()
        costs = case_costs(
            space.controller_of(space.log_gains(z)), cases, config.objective, all_devices=False
        )
        diff = eqx.filter(costs, eqx.is_inexact_array)
        terms = jax.tree.map(lambda c, x: jnp.sum(jnp.where(c != 0, c * x, 0.0)), cotangent, diff)
        return sum(jax.tree.leaves(terms))

    return jax.grad(fn)(z)


@eqx.filter_jit
def _chunk_forward(config: TuneConfig, z, cases):
    """(CaseCosts of one chunk's cases, their vector-Jacobian product function): the chunk's
    forward pass, whose residuals (the solver's checkpoints) its reverse pass `_chunk_pullback`
    takes, so that the forward pass is not computed a second time."""

    def fn(z):
        space = config.space()
        return case_costs(
            space.controller_of(space.log_gains(z)), cases, config.objective, all_devices=False
        )

    return eqx.filter_vjp(fn, z)


@eqx.filter_jit
def _chunk_pullback(vjp_fn, cotangent):
    """d/dz of sum_i <cotangent_i, costs_i(z)> over one chunk, from `_chunk_forward`'s
    function (``cotangent``: an array for every inexact leaf of the costs, None elsewhere)."""
    (grad,) = vjp_fn(cotangent)
    return grad


def gradient_chunks(n: int, chunk: int, n_devices: int) -> int:
    """Cases per reverse pass of `chunked_value_and_grad` over ``n`` cases on ``n_devices``
    devices: at most ``chunk``, and small enough that every device gets a chunk (whole ensemble
    groups of `GROUP_SIZE`); 0: one reverse pass over all cases (``n <= chunk`` on one device
    or in one group, or ``n`` not a multiple of `GROUP_SIZE`)."""
    if n % GROUP_SIZE or (n <= chunk and (n_devices < 2 or n < 2 * GROUP_SIZE)):
        return 0
    return min(chunk, GROUP_SIZE * math.ceil(n / (GROUP_SIZE * n_devices)))


def _on_devices(work, items, devices):
    """``work(item, device)`` for every item, item i on ``devices[i % len(devices)]``; each
    device's items one after the other in a thread of its own, so that the devices compute
    at the same time (called from one thread, a CPU device's program runs after the
    other's). Returns the results in the order of ``items``."""
    if len(devices) < 2:
        return [work(item, devices[0]) for item in items]
    lanes = [list(range(d, len(items), len(devices))) for d in range(len(devices))]

    def lane(d):
        return [(i, work(items[i], devices[d])) for i in lanes[d]]

    with ThreadPoolExecutor(max_workers=len(devices)) as pool:
        done = [r for rs in pool.map(lane, range(len(devices))) for r in rs]
    return [r for _, r in sorted(done, key=lambda ir: ir[0])]


def chunked_value_and_grad(config: TuneConfig, z, cases, ref, devices=None):
    """((objective, CaseCosts), d objective / dz) with the reverse pass over at most
    ``config.objective.gradient_chunk`` cases at a time, spread over ``devices`` (default:
    every local device; `gradient_chunks`): the costs of every case, the cotangent
    d objective / d costs (the objective is not a sum over cases: CVaR, limits), then the sum
    over chunks of that cotangent's vector-Jacobian product through each chunk's simulation,
    the chunks of different devices computed at the same time (one thread per device). With at
    most one chunk per device, each chunk's forward pass gives its cases' costs and keeps its
    residuals for its reverse pass (`_kept_forward_value_and_grad`), so every case is simulated
    forward once; with more chunks, a forward pass over every case comes first and each chunk's
    reverse pass computes its own forward pass again (memory bounded by the chunk). The same
    gradient as one reverse pass (each case's costs depend only on its ensemble group, which a
    chunk keeps whole), to round-off. One reverse pass when `gradient_chunks` says so. The last
    chunk is filled up with cases from the start, their cotangents zero (one compiled program
    for every chunk; compiled once per device)."""
    devices = list(jax.local_devices() if devices is None else devices)
    n = cases.n_cases
    size = gradient_chunks(n, config.objective.gradient_chunk, len(devices))
    if not size:
        return _value_and_grad(config, z, cases, ref)
    starts = list(range(0, n, size))
    if len(starts) <= len(devices):
        return _kept_forward_value_and_grad(config, z, cases, ref, starts, size, devices)
    space = config.space()
    costs = _costs(config, space.log_gains(z), cases)
    value, cotangent = _costs_cotangent(config, costs, ref)

    def work(start, device):
        idx = _chunk_rows(start, size, n)
        part = _chunk_cotangent(cotangent, start, size, n)
        arrays, static = eqx.partition((z, cases.take(idx), part), eqx.is_array)
        args = eqx.combine(jax.device_put(arrays, device), static)
        return jax.device_get(_chunk_grad(config, *args))

    return (value, costs), _sum_grads(_on_devices(work, starts, devices[: len(starts)]))


def _chunk_rows(start: int, size: int, n: int) -> np.ndarray:
    """Case indices of the chunk at ``start``, filled up with cases from the start past ``n``."""
    return np.arange(start, start + size) % n


def _chunk_cotangent(cotangent, start: int, size: int, n: int):
    """The chunk's rows of the cotangent of every case's costs, zero on its filling."""
    idx, live = _chunk_rows(start, size, n), jnp.asarray(np.arange(start, start + size) < n)
    return jax.tree.map(lambda c: jnp.where(live, c[idx], 0.0), cotangent)


def _sum_grads(grads: list):
    """The chunks' gradients summed in order."""
    return jax.tree.map(lambda *g: jnp.asarray(sum(g[1:], g[0])), *grads)


def _kept_forward_value_and_grad(config: TuneConfig, z, cases, ref, starts, size, devices):
    """`chunked_value_and_grad` with at most one chunk per device: each device's chunk makes
    its forward pass once and keeps its residuals for its reverse pass (`_chunk_forward`,
    `_chunk_pullback`); the costs of all cases come from those forward passes. Memory: each
    device holds its chunk's residuals from its forward pass to its reverse pass, as the reverse
    pass of one program over the chunk does."""
    n = cases.n_cases

    def forward(start, device):
        arrays, static = eqx.partition((z, cases.take(_chunk_rows(start, size, n))), eqx.is_array)
        return _chunk_forward(config, *eqx.combine(jax.device_put(arrays, device), static))

    kept = _on_devices(forward, starts, devices[: len(starts)])
    # the chunks in order, the last one's filling dropped: every case once
    costs = jax.tree.map(
        lambda *xs: jax.device_put(np.concatenate([np.asarray(x) for x in xs])[:n]),
        *[c for c, _ in kept],
    )
    value, cotangent = _costs_cotangent(config, costs, ref)

    def backward(i, device):
        part = jax.device_put(_chunk_cotangent(cotangent, starts[i], size, n), device)
        return jax.device_get(_chunk_pullback(kept[i][1], part))

    grads = _on_devices(backward, list(range(len(starts))), devices[: len(starts)])
    return (value, costs), _sum_grads(grads)


@eqx.filter_jit
def _adam_step(config: TuneConfig, z, opt_state, grads):
    leaves = jax.tree.leaves(grads)
    grad_norm = jnp.sqrt(sum(jnp.sum(jnp.where(jnp.isfinite(g), g, 0.0) ** 2) for g in leaves))
    grads = jax.tree.map(lambda g: jnp.where(jnp.isfinite(g), g, jnp.nan), grads)
    updates, opt_state = make_optimizer(config).update(grads, opt_state, z)
    return optax.apply_updates(z, updates), opt_state, grad_norm


@eqx.filter_jit
def _lbfgs_step(config: TuneConfig, z, opt_state, value, grad, cases, ref):
    """One L-BFGS step with the backtracking line search from (value, grad) at z (the trials
    are forward evaluations of the objective)."""

    def value_fn(x):
        return _objective_z(x, config, cases, ref)[0]

    updates, opt_state = make_optimizer(config).update(
        grad, opt_state, z, value=value, grad=grad, value_fn=value_fn
    )
    return optax.apply_updates(z, updates), opt_state


def population_losses(config: TuneConfig, cases, ref, zs) -> np.ndarray:
    """Objective of each candidate row of ``zs`` (P, 12) on ``cases`` with the normalising
    ``ref`` (``config``: a `TuneConfig.objective_key`): one batched call (a task of a
    cluster)."""
    return np.asarray(_population(config, jnp.asarray(zs), cases, ref), dtype=float)


def population_groups(p: int, n_cases: int, slots: int) -> list[tuple[int, int]]:
    """Consecutive groups [a, b) of ``p`` candidates, at most ``slots`` of them, as even as
    possible, each boundary at a multiple of GROUP_SIZE / gcd(n_cases, GROUP_SIZE) candidates:
    the batched call lays the candidates' ``n_cases`` cases out one after the other in
    ensemble groups of GROUP_SIZE, so every group of cases then lies inside one candidate
    group and the groups' numbers are those of the whole population's call."""
    step = GROUP_SIZE // math.gcd(int(n_cases), GROUP_SIZE)
    units = -(-int(p) // step)
    k = max(1, min(int(slots), units))
    bounds = [min(p, step * (units * i // k)) for i in range(k + 1)]
    return [(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]


@eqx.filter_jit
def _population(config: TuneConfig, zs, cases, ref):
    """Objective of each candidate row of ``zs`` (P, 12): one simulate_batch call over
    P x n cases with per-case controllers."""
    space = config.space()
    p, n = zs.shape[0], cases.n_cases
    z = _unflat(jnp.repeat(zs, n, axis=0), space.names)  # (P n, 4) per gain
    costs = case_costs(
        space.controller_of(space.log_gains(z)), tile_cases(cases, p), config.objective
    )
    per = jax.tree.map(lambda x: x.reshape(p, n), costs)
    return jax.vmap(lambda c: objective_of_costs(c, ref, config.objective))(per)


def tune(
    config: TuneConfig,
    out: str | Path | None = None,
    resume: bool = False,
    progress: bool = True,
    executor: Executor | None = None,
) -> TuneResult:
    """Tune the gains of ``config.controller`` (see `Tuner.run`; ``executor``: where CMA-ES
    populations are evaluated)."""
    return Tuner(config, executor=executor).run(out, resume=resume, progress=progress)


def save_checkpoint(out, config: TuneConfig, step: int, z, state, history) -> None:
    """Write OUT/checkpoint.eqx (z and the optax state; exact) or OUT/checkpoint_cma.pkl (the
    CMA-ES object; the hybrid's also z and its L-BFGS state), and OUT/checkpoint.json
    (iteration, config, history)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if config.method in POPULATION_METHODS:
        tmp = out / (CHECKPOINT_CMA + ".tmp")
        # cmaes.CMA drops its random generator when pickled: keep the generator's state too
        saved = {**state, "rng": state["cma"]._rng.get_state()}
        if config.method == "hybrid":
            saved["z"] = jax.tree.map(np.asarray, z)
            saved["lbfgs"] = jax.tree.map(np.asarray, state["lbfgs"])
        tmp.write_bytes(pickle.dumps(saved))
        tmp.replace(out / CHECKPOINT_CMA)
    else:
        tmp = out / (CHECKPOINT_ARRAYS + ".tmp")
        eqx.tree_serialise_leaves(tmp, (z, state))
        tmp.replace(out / CHECKPOINT_ARRAYS)
    doc = {"step": step, "config": config.to_dict(), "history": history}
    tmp = out / (CHECKPOINT_STATE + ".tmp")
    tmp.write_text(json.dumps(doc))
    tmp.replace(out / CHECKPOINT_STATE)


def load_checkpoint(out, config: TuneConfig, z, state):
    """(iteration, z, state, history) from OUT's checkpoint; the config must match."""
    out = Path(out)
    try:
        doc = json.loads((out / CHECKPOINT_STATE).read_text())
    except FileNotFoundError:
        raise ValueError(f"no checkpoint in {out} ({CHECKPOINT_STATE} missing).") from None
    saved = TuneConfig.from_dict(doc["config"])
    if saved != config:
        diff = {
            k: (v, getattr(config, k)) for k, v in asdict(saved).items() if v != asdict(config)[k]
        }
        raise ValueError(
            f"checkpoint in {out} was written with a different config (saved, requested): {diff}."
        )
    if config.method in POPULATION_METHODS:
        state = pickle.loads((out / CHECKPOINT_CMA).read_bytes())
        state["cma"]._rng.set_state(state.pop("rng"))
        z = _unflat(state["best"], config.space().names)
        if config.method == "hybrid":
            z = jax.tree.map(jnp.asarray, state.pop("z"))
            state["lbfgs"] = jax.tree.map(jnp.asarray, state["lbfgs"])
    else:
        z, state = eqx.tree_deserialise_leaves(out / CHECKPOINT_ARRAYS, (z, state))
    return int(doc["step"]), z, state, doc["history"]

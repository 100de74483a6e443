"""The tuning loop: optax over log-gains, non-finite-gradient guard, checkpoints, resume."""

from __future__ import annotations

import functools
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from ...model import AbstractController
from ._cases import DEFAULT_THRUST_TO_WEIGHT
from ._objective import GainSpace, ObjectiveConfig, cases_for, objective

OPTIMIZERS = ("adam", "sgd")
SCHEDULES = ("cosine", "constant")
CHECKPOINT_ARRAYS = "checkpoint.eqx"
CHECKPOINT_STATE = "checkpoint.json"


@dataclass(frozen=True)
class TuneConfig:
    """Everything that defines a tuning run (recorded in meta.json and the checkpoint).

    Attributes:
        controller: "afbl" or "fbl".
        objective: the `ObjectiveConfig` (objective, risk, weights, solver tolerances).
        n_cases: training cases for the robust objective (ignored for nominal: the canonical 4).
        seed: seed of the training cases.
        steps: optimiser steps.
        optimizer: "adam" (default) or "sgd"; learning_rate: peak step size in log-gain units;
        schedule: "cosine" (decay to 10 % over ``steps``, default) or "constant".
        clip_norm: global-norm gradient clipping threshold.
        lower, upper: gain box as factors of the paper's gains.
        thrust_to_weight: rotor limit (max thrust / nominal weight); None = unlimited.
        checkpoint_every: write a checkpoint every this many steps (0: never).
    """

    controller: str = "afbl"
    objective: ObjectiveConfig = field(default_factory=ObjectiveConfig)
    n_cases: int = 64
    seed: int = 0
    steps: int = 100
    optimizer: str = "adam"
    learning_rate: float = 0.05
    schedule: str = "cosine"
    clip_norm: float = 1.0
    lower: float = 0.1
    upper: float = 10.0
    thrust_to_weight: float | None = DEFAULT_THRUST_TO_WEIGHT
    checkpoint_every: int = 10

    def __post_init__(self):
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(
                f"unknown optimizer {self.optimizer!r}; allowed: {', '.join(OPTIMIZERS)}."
            )
        if self.schedule not in SCHEDULES:
            raise ValueError(
                f"unknown schedule {self.schedule!r}; allowed: {', '.join(SCHEDULES)}."
            )
        if self.steps < 0 or self.n_cases < 1 or self.checkpoint_every < 0:
            raise ValueError(
                "need steps >= 0, n_cases >= 1, checkpoint_every >= 0; got "
                f"{self.steps}, {self.n_cases}, {self.checkpoint_every}."
            )
        if not (self.learning_rate > 0 and self.clip_norm > 0):
            raise ValueError("learning_rate and clip_norm must be > 0.")
        if self.thrust_to_weight is not None and not self.thrust_to_weight > 1.0:
            raise ValueError(
                f"thrust_to_weight must be > 1 (or None), got {self.thrust_to_weight}."
            )
        self.space()  # validates controller and box

    def space(self) -> GainSpace:
        return GainSpace(self.controller, lower=self.lower, upper=self.upper)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> TuneConfig:
        d = dict(d)
        d["objective"] = ObjectiveConfig(**d["objective"])
        return cls(**d)


def make_optimizer(config: TuneConfig) -> optax.GradientTransformation:
    """zero_nans -> global-norm clipping -> Adam/SGD with the schedule."""
    if config.schedule == "cosine":
        lr = optax.cosine_decay_schedule(config.learning_rate, max(config.steps, 1), alpha=0.1)
    else:
        lr = optax.constant_schedule(config.learning_rate)
    base = optax.adam(lr) if config.optimizer == "adam" else optax.sgd(lr)
    return optax.chain(optax.zero_nans(), optax.clip_by_global_norm(config.clip_norm), base)


@dataclass
class TuneResult:
    """Outcome of `tune`: final log-gains, controller, per-step history, config."""

    params: dict
    controller: AbstractController
    history: list[dict]
    config: TuneConfig
    opt_state: Any = None

    @property
    def initial_loss(self) -> float:
        return self.history[0]["loss"]

    @property
    def final_loss(self) -> float:
        return self.history[-1]["loss"]


class Tuner:
    """Holds the jitted loss/gradient and update functions for one `TuneConfig` (build once,
    reuse: no retracing across steps or across `run` calls)."""

    def __init__(self, config: TuneConfig, cases=None):
        self.config = config
        self.space = config.space()
        self.cases = (
            cases
            if cases is not None
            else cases_for(config.objective, config.n_cases, config.seed, config.thrust_to_weight)
        )
        self.optimizer = make_optimizer(config)
        self.value_and_grad = functools.partial(_value_and_grad, config)
        self.update = functools.partial(_update, config)

    def init(self) -> tuple[dict, Any]:
        params = self.space.init_params()
        return params, self.optimizer.init(params)

    def _row(self, step, params, loss, costs, grad_norm, nonfinite) -> dict:
        row = {
            "step": step,
            "loss": float(loss),
            "grad_norm": float(grad_norm),
            "nonfinite_grad": int(nonfinite),
            "ise_attitude": float(np.mean(costs.ise_attitude)),
            "ise_altitude": float(np.mean(costs.ise_altitude)),
            "effort": float(np.mean(costs.effort)),
            "saturation": float(np.mean(costs.saturation)),
            "failed": int(np.sum(costs.failed)),
        }
        for name in self.space.names:
            for ch, v in zip(
                ("phi", "theta", "psi", "z"), np.exp(np.asarray(params[name])), strict=True
            ):
                row[f"{name}_{ch}"] = float(v)
        return row

    def run(
        self,
        out: str | Path | None = None,
        resume: bool = False,
        progress: bool = True,
        stop_after: int | None = None,
        log=print,
    ) -> TuneResult:
        """Optimise for ``config.steps`` steps (or stop after ``stop_after`` steps, for tests
        of resuming). Checkpoints go to ``out`` every ``checkpoint_every`` steps; ``resume``
        continues from ``out``'s checkpoint (same config required) with the same result as an
        uninterrupted run. The history has one row per step (loss and gradient at the gains of
        that step) plus a last row for the final gains."""
        cfg = self.config
        params, opt_state = self.init()
        history: list[dict] = []
        start = 0
        if resume:
            if out is None:
                raise ValueError("resume needs the output folder holding the checkpoint.")
            start, params, opt_state, history = load_checkpoint(out, cfg, params, opt_state)
            log(f"resumed from {Path(out) / CHECKPOINT_STATE} at step {start}")
        end = cfg.steps if stop_after is None else min(cfg.steps, start + stop_after)
        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=cfg.steps, initial=start, desc="tune", unit="step")
        for step in range(start, end):
            (loss, costs), grads = self.value_and_grad(params, self.cases)
            new_params, opt_state, gnorm, nonfinite = self.update(params, opt_state, grads)
            row = self._row(step, params, loss, costs, gnorm, nonfinite)
            history.append(row)
            if row["nonfinite_grad"]:
                log(
                    f"step {step}: {row['nonfinite_grad']} non-finite gradient entries "
                    "zeroed (optax.zero_nans) before the update"
                )
            if not math.isfinite(row["loss"]):
                log(f"step {step}: non-finite loss {row['loss']}")
            params = new_params
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{row['loss']:.4e}", gnorm=f"{row['grad_norm']:.2e}")
            done = step + 1
            if (
                out is not None
                and cfg.checkpoint_every
                and (done % cfg.checkpoint_every == 0 or done == end)
            ):
                save_checkpoint(out, cfg, done, params, opt_state, history)
        if bar is not None:
            bar.close()
        if end == cfg.steps:
            (loss, costs), grads = self.value_and_grad(params, self.cases)
            _, _, gnorm, nonfinite = self.update(params, opt_state, grads)
            history.append(self._row(cfg.steps, params, loss, costs, gnorm, nonfinite))
        return TuneResult(params, self.space.controller_of(params), history, cfg, opt_state)


@functools.partial(jax.jit, static_argnums=0)
def _value_and_grad(config: TuneConfig, params, cases):
    """((objective, CaseCosts), d objective / d log-gains); compiled once per config (a frozen,
    hashable dataclass) and case-batch shape, shared by every `Tuner` with that config."""
    space = config.space()
    return jax.value_and_grad(objective, has_aux=True)(params, space, cases, config.objective)


@functools.partial(jax.jit, static_argnums=0)
def _update(config: TuneConfig, params, opt_state, grads):
    """One optimiser step: count non-finite gradient entries (logged by the caller), turn them
    into NaN so `optax.zero_nans` zeroes them, clip, Adam/SGD, project onto the gain box."""
    lo, hi = config.space().bounds()
    leaves = jax.tree.leaves(grads)
    nonfinite = sum(jnp.sum(~jnp.isfinite(g)) for g in leaves)
    grad_norm = jnp.sqrt(sum(jnp.sum(jnp.where(jnp.isfinite(g), g, 0.0) ** 2) for g in leaves))
    grads = jax.tree.map(lambda g: jnp.where(jnp.isfinite(g), g, jnp.nan), grads)
    updates, opt_state = make_optimizer(config).update(grads, opt_state, params)
    params = optax.projections.projection_box(optax.apply_updates(params, updates), lo, hi)
    return params, opt_state, grad_norm, nonfinite


def tune(
    config: TuneConfig, out: str | Path | None = None, resume: bool = False, progress: bool = True
) -> TuneResult:
    """Tune the gains of ``config.controller`` (see `Tuner.run`)."""
    return Tuner(config).run(out, resume=resume, progress=progress)


def save_checkpoint(out, config: TuneConfig, step: int, params, opt_state, history) -> None:
    """Write OUT/checkpoint.eqx (params, optimiser state; exact) and OUT/checkpoint.json."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / (CHECKPOINT_ARRAYS + ".tmp")
    eqx.tree_serialise_leaves(tmp, (params, opt_state))
    tmp.replace(out / CHECKPOINT_ARRAYS)
    doc = {"step": step, "config": config.to_dict(), "history": history}
    tmp = out / (CHECKPOINT_STATE + ".tmp")
    tmp.write_text(json.dumps(doc))
    tmp.replace(out / CHECKPOINT_STATE)


def load_checkpoint(out, config: TuneConfig, params, opt_state):
    """(step, params, opt_state, history) from OUT's checkpoint; the config must match."""
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
    params, opt_state = eqx.tree_deserialise_leaves(out / CHECKPOINT_ARRAYS, (params, opt_state))
    return int(doc["step"]), params, opt_state, doc["history"]

"""Mixed continuous/discrete optimiser of a PPTBF parameter vector against any loss callable.

The paper alternates Powell on the continuous parameters with Bayesian optimisation on the discrete ones. Here:

* continuous: a derivative-free local method from nlopt (default LN_SBPLX, Subplex, robust on the noisy,
  piecewise-constant PPTBF loss; LN_BOBYQA / LN_NELDERMEAD selectable) on the continuous entries mapped to
  [0, 1] (log scale for the period and the aspect ratio). `nlopt.opt` does not pickle, so it is built inside.
* discrete: coordinate-wise exhaustive sweeps. The six discrete entries have 4 to 18 useful values each
  (kernel counts and stripe frequency limited to the database range 0..8), so one sweep of every value of every
  entry costs ~50 evaluations, the price of a few Bayesian-optimisation steps, with no surrogate model to fit,
  no extra dependency and a deterministic result; values irrelevant under the current mixture are skipped.
* structure moves: the period, aspect ratio and orientation set the whole layout, and a local method with small
  steps does not jump between their basins; `structure_sweep` tries period x {1/2, 1/sqrt2, sqrt2, 2}, aspect
  x {1/2, 2} and rotations by 45/90/135 degrees (9 evaluations) next to each discrete sweep (optional).
* multi-start: `explore` gives a starting vector a short local search on its own small budget; the caller
  explores several re-ranked entries (both polarities) and runs the main search from the most promising basin.
* a budget object counts evaluations and time, caches repeated vectors and keeps the best vector ever seen, so
  any stop (budget, nlopt failure) returns the best-ever point.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from pptbf_db import pptbf as pp

logger = logging.getLogger(__name__)

Loss = Callable[[np.ndarray], float]

_I = pp.PARAM_INDEX
#: continuous entries optimised (threshold is excluded: it is set from the target's white fraction)
OPT_CONT_IDX = np.array([i for i in pp.CONTINUOUS_IDX if i != _I["threshold"]], dtype=np.int64)
#: entries handled on a log scale
LOG_PARAMS = ("resolution", "aspect_ratio")
#: optimisation bounds narrower than the valid ranges where the valid range is degenerate
OPT_BOUNDS: dict[str, tuple[float, float]] = {
    "aspect_ratio": (0.1, 10.0),
    "distortion_base": (0.0, 0.1),
    "distortion_amplitude": (0.0, 2.0),
}
#: entries that move the whole pattern (period, orientation, aspect): smaller initial steps
STRUCTURE_IDX = np.array([_I[n] for n in ("resolution", "rotation", "aspect_ratio")], dtype=np.int64)
STRUCTURE_STEP = 0.25
#: values tried per discrete entry (kernel counts and frequency limited to the database's sampling range)
DISCRETE_VALUES: dict[str, tuple[int, ...]] = {
    "tiling": tuple(range(18)),
    "window_shape": (0, 1, 2, 3),
    "feature_mixture": (0, 1, 2, 3, 4),
    "feature_kernel_min": tuple(range(9)),
    "feature_kernel_max": tuple(range(9)),
    "feature_frequency": tuple(range(9)),
}
#: discrete entries that only matter when kernels are used (mixture != 0)
_FEATURE_DISC = ("feature_kernel_min", "feature_kernel_max", "feature_frequency")


class BudgetExhausted(Exception):
    """Raised inside an objective when the evaluation or time budget is spent."""


@dataclass
class Budget:
    """Counts evaluations of `loss`, enforces limits, caches repeats and keeps the best vector ever seen."""

    loss: Loss
    max_evals: int
    deadline: float
    evaluations: int = 0
    best_params: np.ndarray | None = None
    best_loss: float = math.inf
    history: list[float] = field(default_factory=list)
    _cache: dict = field(default_factory=dict)

    @property
    def exhausted(self) -> bool:
        """True when no evaluation is left."""
        return self.evaluations >= self.max_evals or time.perf_counter() >= self.deadline

    def seed(self, params: np.ndarray, value: float) -> None:
        """Record an already-evaluated vector (not counted) as the starting best."""
        p = pp.clip_params(params)
        self._cache[np.round(p, 9).tobytes()] = float(value)
        if value < self.best_loss:
            self.best_loss, self.best_params = float(value), p.copy()

    def __call__(self, params: np.ndarray) -> float:
        """Loss of a (clipped) parameter vector; raises BudgetExhausted when over budget."""
        p = pp.clip_params(params)
        key = np.round(p, 9).tobytes()
        if key in self._cache:
            return self._cache[key]
        if self.exhausted:
            raise BudgetExhausted
        value = float(self.loss(p))
        if not np.isfinite(value):
            value = 1e30
        self.evaluations += 1
        self._cache[key] = value
        if value < self.best_loss:
            self.best_loss, self.best_params = value, p.copy()
        self.history.append(self.best_loss)
        return value


@dataclass(frozen=True)
class ContinuousSpace:
    """Maps the optimised continuous entries of a 29-vector to z in [0, 1]^n and back."""

    lo: np.ndarray
    hi: np.ndarray
    log: np.ndarray
    idx: np.ndarray = field(default_factory=lambda: OPT_CONT_IDX.copy())

    @classmethod
    def for_width(cls, width: int, frozen: tuple[str, ...] = ()) -> "ContinuousSpace":
        """The space for masks `width` pixels wide (period between 2 px and the whole width), without the
        `frozen` entries (kept at the starting vector's values)."""
        lo, hi, lg = [], [], []
        idx = np.array([i for i in OPT_CONT_IDX if pp.PARAM_NAMES[i] not in frozen], dtype=np.int64)
        for i in idx:
            s = pp.PARAM_SPECS[i]
            a, b = OPT_BOUNDS.get(s.name, (s.lo, s.hi))
            if s.name == "resolution":
                a, b = 2.0, float(max(4, width))
            is_log = s.name in LOG_PARAMS
            lo.append(math.log(a) if is_log else a)
            hi.append(math.log(b) if is_log else b)
            lg.append(is_log)
        return cls(np.array(lo), np.array(hi), np.array(lg, dtype=bool), idx)

    def encode(self, params: np.ndarray) -> np.ndarray:
        """z in [0, 1]^n of the optimised continuous entries."""
        v = np.asarray(params, dtype=np.float64)[self.idx].copy()
        v[self.log] = np.log(np.maximum(v[self.log], 1e-6))
        return np.clip((v - self.lo) / (self.hi - self.lo), 0.0, 1.0)

    def decode(self, z: np.ndarray, base: np.ndarray) -> np.ndarray:
        """A copy of `base` with the optimised continuous entries taken from z."""
        v = self.lo + np.clip(z, 0.0, 1.0) * (self.hi - self.lo)
        v[self.log] = np.exp(v[self.log])
        out = np.array(base, dtype=np.float64)
        out[self.idx] = v
        return out


def continuous_step(budget: Budget, x0: np.ndarray, space: ContinuousSpace, max_evals: int, *,
                    algorithm: str = "LN_SBPLX", step: float = 0.08) -> np.ndarray:
    """Local derivative-free refinement of the continuous entries from x0; returns the best vector seen."""
    import nlopt  # built here: nlopt.opt does not pickle

    z0 = space.encode(x0)
    opt = nlopt.opt(getattr(nlopt, algorithm), z0.size)
    opt.set_lower_bounds(np.zeros(z0.size))
    opt.set_upper_bounds(np.ones(z0.size))
    steps = np.full(z0.size, step)
    steps[np.isin(space.idx, STRUCTURE_IDX)] = step * STRUCTURE_STEP
    opt.set_initial_step(steps)
    opt.set_maxeval(max(1, int(max_evals)))
    opt.set_xtol_rel(1e-4)
    base = np.array(x0, dtype=np.float64)

    def objective(z, grad):
        try:
            return budget(space.decode(z, base))
        except BudgetExhausted:
            raise nlopt.ForcedStop from None

    opt.set_min_objective(objective)
    try:
        opt.optimize(z0)
    except (nlopt.ForcedStop, nlopt.RoundoffLimited, RuntimeError, ValueError) as exc:
        logger.debug("continuous step stopped: %r", exc)
    return budget.best_params


def discrete_sweep(budget: Budget, x0: np.ndarray, rng: np.random.Generator,
                   frozen: tuple[str, ...] = ()) -> np.ndarray:
    """Coordinate-wise exhaustive search over the discrete entries but `frozen` (random order), accepting
    improvements."""
    best = pp.clip_params(x0)
    best_loss = budget(best)
    names = [n for n in DISCRETE_VALUES if n not in frozen]
    for j in rng.permutation(len(names)):
        name = names[j]
        i = _I[name]
        if name in _FEATURE_DISC and int(best[_I["feature_mixture"]]) == 0:
            continue
        for v in DISCRETE_VALUES[name]:
            if v == int(best[i]):
                continue
            cand = best.copy()
            cand[i] = v
            if int(cand[_I["feature_mixture"]]) == 0 and int(cand[_I["window_shape"]]) == 0:
                continue  # flat image (spec §2.7)
            if name == "feature_kernel_min" and v > cand[_I["feature_kernel_max"]]:
                cand[_I["feature_kernel_max"]] = v
            if name == "feature_kernel_max" and v < cand[_I["feature_kernel_min"]]:
                cand[_I["feature_kernel_min"]] = v
            loss = budget(cand)
            if loss < best_loss:
                best, best_loss = pp.clip_params(cand), loss
    return best


#: relative moves of the layout entries tried by `structure_sweep` (period and aspect: factors; rotation: added)
STRUCTURE_MOVES: dict[str, tuple[float, ...]] = {
    "resolution": (0.5, 0.7071, 1.4142, 2.0),
    "aspect_ratio": (0.5, 2.0),
    "rotation": (0.25, 0.5, 0.75),
}


def structure_sweep(budget: Budget, x0: np.ndarray, width: int) -> np.ndarray:
    """Try large moves of the period, aspect ratio and orientation (coordinate-wise, accepting improvements)."""
    best = pp.clip_params(x0)
    best_loss = budget(best)
    for name, moves in STRUCTURE_MOVES.items():
        i = _I[name]
        base = best.copy()
        for m in moves:
            cand = base.copy()
            if name == "rotation":
                cand[i] = (base[i] + m) % 2.0
            elif name == "resolution":
                cand[i] = float(np.clip(round(base[i] * m), 2, max(4, width)))
            else:
                cand[i] = float(np.clip(base[i] * m, *OPT_BOUNDS["aspect_ratio"]))
            loss = budget(cand)
            if loss < best_loss:
                best, best_loss = pp.clip_params(cand), loss
    return best


@dataclass
class OptSettings:
    """How `optimise` spends its budget."""

    rounds: int = 3
    max_evals: int = 300
    time_budget_s: float = 50.0
    algorithm: str = "LN_SBPLX"
    step: float = 0.08
    seed: int = 0
    continuous_share: float = 0.6
    skip_idle_sweeps: bool = True
    structure_moves: bool = False
    frozen: tuple[str, ...] = ()      # entries kept at the start's values (e.g. the layout found by lattice analysis)


def optimise(loss: Loss, x0: np.ndarray, width: int, settings: OptSettings = OptSettings(),
             budget: Budget | None = None) -> Budget:
    """Alternate continuous refinement and discrete sweeps from x0, keeping the best ever; returns the budget."""
    rng = np.random.default_rng(settings.seed)
    if budget is None:
        budget = Budget(loss, settings.max_evals, time.perf_counter() + settings.time_budget_s)
    space = ContinuousSpace.for_width(width, settings.frozen)
    x = pp.clip_params(x0)
    sweep = True
    try:
        budget(x)
        for r in range(max(1, settings.rounds)):
            before = budget.best_loss
            left = budget.max_evals - budget.evaluations
            share = settings.continuous_share if sweep else 1.0
            per_round = max(15, int(share * left / max(1, settings.rounds - r)))
            x = continuous_step(budget, x, space, per_round, algorithm=settings.algorithm, step=settings.step)
            if sweep or not settings.skip_idle_sweeps:
                mid = budget.best_loss
                x = discrete_sweep(budget, x, rng, settings.frozen)
                if settings.structure_moves:
                    x = structure_sweep(budget, x, width)
                sweep = budget.best_loss < mid      # a sweep that found nothing is skipped next round
            else:
                sweep = True
            logger.debug("round %d: loss %.4f -> %.4f (%d evals)", r, before, budget.best_loss, budget.evaluations)
            if budget.exhausted:
                break
    except BudgetExhausted:
        pass
    return budget


def explore(budget: Budget, x0: np.ndarray, width: int, settings: OptSettings = OptSettings()) -> Budget:
    """Short local search from x0 on its own (small) budget: a continuous step, then the structure moves."""
    space = ContinuousSpace.for_width(width)
    try:
        budget(pp.clip_params(x0))
        x = continuous_step(budget, x0, space, max(1, budget.max_evals - budget.evaluations - 9),
                            algorithm=settings.algorithm, step=settings.step)
        if settings.structure_moves:
            structure_sweep(budget, x, width)
    except BudgetExhausted:
        pass
    return budget

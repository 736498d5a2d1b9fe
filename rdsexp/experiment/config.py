"""From a composed Hydra config to validated numerics objects, before any compute.

Every check raises `ConfigError` with one line naming the key, the value and what is allowed.
The numerics' own ValueErrors (shapes, PSD, NaN) are re-raised with the config key in front.
"""
from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, ListConfig, OmegaConf

from ..errors import ConfigError, one_line
from ..numerics.distributions import from_spec
from ..numerics.enkf import VARIANTS, AdaptiveInflation, EnKF, check_covariance, output_delay, truth_map, xi_support
from ..numerics.modeling import COVARIANCES, mls_input
from ..numerics.online import MEMORIES, OBSERVERS, STARTS, OnlineSettings
from ..numerics.simulation import ESTIMATES, Recorded, check_estimate
from ..numerics.synthesis import METHODS, check_options
from ..numerics.systems import AffineRandomSystem, MomentModel
from ..numerics.verdict import window_start
from .data import RecordedData
from .data import load as load_data
from .metrics import objectives

TRACKING_LEVELS = ("off", "summary", "full")
FEEDBACK_MODES = ("none", "nominal", "auto")     # identification.feedback, or a gain F (m x n)
OBSERVER_XI = ("random_walk", "model")   # closed_loop.observer_xi: the paper's xi random walk, or i.i.d. model draws
ESTIMATORS = ("paper", "simulated")      # identification.estimator: eq. (sample-mean), or `numerics.indirect`
REPLICATE_LAWS = ("random_shapes", "normal")    # identification.replicate_laws (or auto: the first for a simulated
                                                # run, the second for a data run)
XI_MODELS = ("random_walk", "iterated")   # identification.xi_model: the paper's, or passes drawing xi i.i.d.
INITIAL_XI = ("guess", "zero")       # enkf.initial.xi: members' xi at identification.xi_guess, or at 0 (the paper)
LOOK_GROWTH = 4                      # closed_loop.paths auto: each look judges 4 times the previous look's paths
XI_SUPPORT = ("project", "free")     # enkf.xi_support: members projected onto the plant family's support box, or not


@contextmanager
def key(name: str):
    """Re-raise a ValueError from inside as a ConfigError about config key `name`."""
    try:
        yield
    except ConfigError:
        raise
    except (ValueError, TypeError) as err:
        raise ConfigError(f"{name}: {err}") from None


def plain(node):
    """OmegaConf node -> plain Python containers (resolved)."""
    return OmegaConf.to_container(node, resolve=True) if isinstance(node, (DictConfig, ListConfig)) else node


def _number(value, name: str, *, integer: bool = False, low=None, high=None, low_open=False) -> float | int:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok and integer:
        ok = float(value).is_integer()
    if ok and low is not None:
        ok = value > low if low_open else value >= low
    if ok and high is not None:
        ok = value <= high
    if not ok:
        kind = "an integer" if integer else "a finite number"
        bounds = "".join([f" {'>' if low_open else '>='} {low}" if low is not None else "",
                          f" and <= {high}" if high is not None else ""])
        raise ConfigError(f"{name}: {value!r} is not allowed, expected {kind}{bounds}")
    return int(value) if integer else float(value)


def get(cfg, name: str):
    """cfg value at dotted `name`, or ConfigError if it is missing."""
    value = OmegaConf.select(cfg, name, default=KeyError)
    if value is KeyError:
        raise ConfigError(f"{name}: missing from the configuration")
    return plain(value)


def _covariance(cfg, name: str, dim: int) -> np.ndarray:
    """A PSD (dim, dim) matrix from a scalar, a diagonal or a matrix at config key `name`."""
    try:
        return check_covariance(name, get(cfg, name), dim)
    except (ValueError, TypeError) as err:
        text = one_line(err, with_type=False)
        raise ConfigError(text if text.startswith(f"{name}:") else
                          f"{name}: {get(cfg, name)!r} is not allowed, expected a scalar, {dim} diagonal entries "
                          f"or a ({dim}, {dim}) matrix of numbers") from None


def system_from(cfg, group: str, xi=None) -> AffineRandomSystem:
    """An AffineRandomSystem from a config group with lists of basis matrices A, B, C, D."""
    mats = {}
    for name in ("A", "B", "C", "D"):
        value = get(cfg, f"{group}.{name}") if name in ("A", "B") else plain(OmegaConf.select(cfg, f"{group}.{name}"))
        if value is not None and not isinstance(value, list):
            raise ConfigError(f"{group}.{name}: expected a list of matrices [{name}0, {name}1, ...], got {value!r}")
        mats[name] = value
    with key(group):
        return AffineRandomSystem(**mats, xi_dist=xi)


INPUT_LEVELS = ("bipolar", "unipolar")


def identification_input(cfg, horizon: int, m: int) -> np.ndarray:
    """The M-sequence of identification.input (levels, amplitude, hold, register_length, taps,
    state, seed; the last three optional, null by default) as (horizon + 1, m)."""
    name = "identification.input"
    node = plain(OmegaConf.select(cfg, name))
    allowed = {"register_length", "amplitude", "levels", "hold", "taps", "state", "seed"}
    if not isinstance(node, dict) or not set(node) <= allowed:
        extra = sorted(set(node) - allowed) if isinstance(node, dict) else node
        raise ConfigError(f"{name}: {extra!r} is not allowed, expected keys among {', '.join(sorted(allowed))}")
    reg = _number(get(cfg, f"{name}.register_length"), f"{name}.register_length", integer=True, low=2, high=32)
    amp = _number(get(cfg, f"{name}.amplitude"), f"{name}.amplitude", low=0, low_open=True)
    levels = node.get("levels", "bipolar")
    if levels not in INPUT_LEVELS:
        raise ConfigError(f"{name}.levels: {levels!r} is not allowed, expected one of {', '.join(INPUT_LEVELS)}")
    hold = _number(node.get("hold", 1), f"{name}.hold", integer=True, low=1)
    seed = node.get("seed")
    if seed is not None:
        seed = _number(seed, f"{name}.seed", integer=True, low=0)
    for sub in ("taps", "state"):
        if node.get(sub) is not None and not (isinstance(node[sub], list) and
                                              all(isinstance(v, int) and not isinstance(v, bool) for v in node[sub])):
            raise ConfigError(f"{name}.{sub}: {node[sub]!r} is not allowed, expected null or a list of integers")
    with key(name):
        return mls_input(horizon, m, reg, amp, levels=levels, hold=hold, taps=node.get("taps"),
                         state=node.get("state"), seed=seed)


GAIN_SOURCES = ("identified", "reported", "fixed")


def _gain_source(cfg, model: AffineRandomSystem, reported) -> tuple[str, np.ndarray | None]:
    """gain.source (default identified) and, for `fixed`, the (m, n) gain gain.F."""
    source = plain(OmegaConf.select(cfg, "gain.source", default="identified"))
    if source not in GAIN_SOURCES:
        raise ConfigError(f"gain.source: {source!r} is not allowed, expected one of {', '.join(GAIN_SOURCES)}")
    if source == "reported" and reported is None:
        raise ConfigError("gain.source: 'reported' is not allowed with model.reported = null (no reported moments)")
    if source != "fixed":
        return source, None
    F = plain(OmegaConf.select(cfg, "gain.F"))
    with key("gain.F"):
        arr = np.asarray(F, dtype=float) if isinstance(F, list) else None
        if arr is None or arr.shape != (model.m, model.n) or not np.all(np.isfinite(arr)):
            raise ValueError(f"{F!r} is not allowed with gain.source = fixed, expected an (m, n) = "
                             f"({model.m}, {model.n}) list of finite numbers")
    return source, arr


@dataclass(frozen=True)
class FilterSettings:
    """conf/enkf: the EnKF on psi = [x; xi] (variant, inflation, relaxation, Q and R, in `enkf`), its
    ensemble size M and its initial ensemble, mean psi0 (n+p,) and covariance P0 (n+p, n+p);
    disturbance: None, or Q_d (m, m), the random-walk increment of the unknown input disturbance the
    loops' EnKF estimates (EnKF.disturbance; `pipeline.loop_observer`; identification never does)."""

    enkf: EnKF
    ensemble_size: int
    psi0: np.ndarray
    P0: np.ndarray
    disturbance: np.ndarray | None = None
    start: str = "zero"        # psi0's xi: enkf.initial.xi (guess | zero), or given (enkf.initial.mean)

    @classmethod
    def from_config(cls, cfg, model: AffineRandomSystem, plant: AffineRandomSystem,
                    xi_guess: np.ndarray) -> FilterSettings:
        dim = model.n + model.p
        M = _number(get(cfg, "enkf.ensemble_size"), "enkf.ensemble_size", integer=True, low=2)
        q_scale = _number(get(cfg, "enkf.q_scale"), "enkf.q_scale", low=0)
        r_scale = _number(get(cfg, "enkf.r_scale"), "enkf.r_scale", low=0)
        Q = q_scale * _process_noise(cfg, model.n, model.p)
        R = r_scale * _covariance(cfg, "enkf.R", model.ny)
        variant = get(cfg, "enkf.variant")
        if variant not in VARIANTS:
            raise ConfigError(f"enkf.variant: {variant!r} is not allowed, expected one of {', '.join(VARIANTS)}")
        inflation = get(cfg, "enkf.inflation")          # rho >= 1, or adaptive with the enkf.adaptive settings
        if variant == "enkf_n" and inflation != 1:
            raise ConfigError(f"enkf.inflation: {inflation!r} is not allowed with enkf.variant=enkf_n, which estimates "
                              f"the inflation itself (Bocquet 2011); expected 1")
        if inflation == "adaptive":
            smoothing = _number(get(cfg, "enkf.adaptive.smoothing"), "enkf.adaptive.smoothing", low=0, high=1)
            low = _number(get(cfg, "enkf.adaptive.low"), "enkf.adaptive.low", low=0, low_open=True)
            inflation = AdaptiveInflation(smoothing, low, _number(get(cfg, "enkf.adaptive.high"), "enkf.adaptive.high",
                                                                  low=low))
        else:
            try:
                inflation = _number(inflation, "enkf.inflation", low=1)
            except ConfigError as err:
                raise ConfigError(f"{err} or adaptive") from None
        relaxation = _number(get(cfg, "enkf.relaxation"), "enkf.relaxation", low=0, high=1)
        if variant in ("etkf", "enkf_n") and np.linalg.eigvalsh(R).min() <= 1e-12 * max(np.abs(R).max(), 1e-300):
            raise ConfigError(f"enkf.R: must be positive definite with enkf.variant={variant} (its transform uses "
                              f"R^-1)")
        support = get(cfg, "enkf.xi_support")
        if support not in XI_SUPPORT:
            raise ConfigError(f"enkf.xi_support: {support!r} is not allowed, expected one of {', '.join(XI_SUPPORT)}")
        bounds = xi_support(model, plant) if support == "project" else None
        disturbance = None
        if get(cfg, "enkf.disturbance") is not None:
            disturbance = _covariance(cfg, "enkf.disturbance", model.m)
            if not disturbance.any():
                raise ConfigError(f"enkf.disturbance: {get(cfg, 'enkf.disturbance')!r} is not allowed, expected null "
                                  f"(off) or a nonzero scale of I_m, m diagonal entries or an (m, m) matrix")
        enkf = EnKF(model, Q, R, variant=variant, inflation=inflation, relaxation=relaxation, xi_bounds=bounds)
        mean = get(cfg, "enkf.initial.mean")
        with key("enkf.initial.mean"):
            psi0 = np.zeros(dim) if mean is None else np.asarray(mean, dtype=float)
            if psi0.shape != (dim,) or not np.all(np.isfinite(psi0)):
                raise ValueError(f"{mean!r} is not allowed, expected null or {dim} finite numbers (n + p)")
        start = get(cfg, "enkf.initial.xi")
        if start not in INITIAL_XI:
            raise ConfigError(f"enkf.initial.xi: {start!r} is not allowed, expected one of {', '.join(INITIAL_XI)}")
        truth = truth_map(model, plant)
        if mean is None and start == "guess" and truth is not None:
            # the members start at the prior guess that the identification feedback is designed on,
            # in the model's xi = T s + t: a filter starting at xi = 0 feeds a wrong x_{k|k-1} back
            psi0[model.n:] = truth[0] @ xi_guess + truth[1]
        return cls(enkf=enkf, ensemble_size=M, psi0=psi0, P0=_covariance(cfg, "enkf.initial.cov", dim),
                   disturbance=disturbance, start="given" if mean is not None else start)


@dataclass(frozen=True)
class IdentificationSettings:
    """conf/identification: the identification run's input (K_id + 1, m), the window K0..K0+K1 the
    distribution is modeled from, and its feedback (none | nominal | auto | given, with its gain
    (m, n)) designed on the nominal guess xi_guess (p_plant,) of the plant's xi."""

    input: np.ndarray
    K0: int
    K1: int
    feedback: str
    gain: np.ndarray | None
    xi_guess: np.ndarray
    covariance: str = "sample"
    prior: str = "zero"         # where xi_guess comes from: a key of PRIORS
    xi_model: str = "random_walk"
    passes: int = 0
    resamples: int = 0          # moving-block bootstrap of the modeling window (0: no uncertainty)
    block: int = 5
    noise_scales: tuple[float, ...] = ()     # enkf.Q's x block and R scaled by each: the moments again
    estimator: str = "paper"    # paper: eq. (sample-mean); simulated: `numerics.indirect` on the paper's as summary
    replicates: int = 400       # simulated: identification runs of the model, one law of xi each
    prior_width: float = 2.5    # simulated: the prior box in the paper estimator's stds (`indirect.prior_box`)
    replicate_laws: str = "random_shapes"   # simulated: the replicates' laws at theta's moments (REPLICATE_LAWS)
    paths: int = 1              # identification runs of a simulated plant (a data run: its recorded paths)

    @classmethod
    def from_config(cls, cfg, plant: AffineRandomSystem, data_run: bool = False) -> IdentificationSettings:
        K_id = _number(get(cfg, "identification.horizon"), "identification.horizon", integer=True, low=1)
        K0 = _number(get(cfg, "identification.K0"), "identification.K0", integer=True, low=0)
        K1 = _number(get(cfg, "identification.K1"), "identification.K1", integer=True, low=0)
        if K0 + K1 > K_id:
            raise ConfigError(f"identification.K1: K0 + K1 = {K0 + K1} is not allowed, must be <= "
                              f"identification.horizon = {K_id}")
        u_id = identification_input(cfg, K_id, plant.m)
        feedback, F_id, xi_guess, prior = _identification_feedback(cfg, plant, data_run)
        covariance = get(cfg, "identification.covariance")
        if covariance not in COVARIANCES:
            raise ConfigError(f"identification.covariance: {covariance!r} is not allowed, expected one of "
                              f"{', '.join(COVARIANCES)}")
        xi_model = get(cfg, "identification.xi_model")
        if xi_model not in XI_MODELS:
            raise ConfigError(f"identification.xi_model: {xi_model!r} is not allowed, expected one of "
                              f"{', '.join(XI_MODELS)}")
        passes = _number(get(cfg, "identification.passes"), "identification.passes", integer=True, low=1)
        resamples = _number(get(cfg, "identification.resamples"), "identification.resamples", integer=True, low=0)
        block = _number(get(cfg, "identification.block"), "identification.block", integer=True, low=1)
        estimator = get(cfg, "identification.estimator")
        if estimator == "auto":
            estimator = "simulated"
        if estimator not in ESTIMATORS:
            raise ConfigError(f"identification.estimator: {estimator!r} is not allowed, expected auto or one of "
                              f"{', '.join(ESTIMATORS)}")
        scales = plain(OmegaConf.select(cfg, "identification.noise_sensitivity", default="auto"))
        if scales == "auto":        # the simulated estimator estimates a data run's noise scale (`Replay.noisy`)
            scales = [0.1, 10.0] if data_run and estimator == "paper" else []
        if not isinstance(scales, list) or len(scales) > 8:
            raise ConfigError(f"identification.noise_sensitivity: {scales!r} is not allowed, expected auto or a list "
                              f"of at most 8 positive factors")
        scales = tuple(_number(v, "identification.noise_sensitivity", low=0, low_open=True) for v in scales)
        replicates = _number(get(cfg, "identification.replicates"), "identification.replicates", integer=True, low=20)
        width = _number(get(cfg, "identification.prior_width"), "identification.prior_width", low=0, low_open=True)
        paths = _number(get(cfg, "identification.paths"), "identification.paths", integer=True, low=1)
        laws = OmegaConf.select(cfg, "identification.replicate_laws", default="auto")
        if laws == "auto":
            # a data run's replicates are one path each, their summaries' covariance scaled down to the mean of the
            # recorded paths; a shape's spread is not noise that averaging removes, and would be scaled down with it
            laws = "normal" if data_run else "random_shapes"
        if laws not in REPLICATE_LAWS:
            raise ConfigError(f"identification.replicate_laws: {laws!r} is not allowed, expected auto or one of "
                              f"{', '.join(REPLICATE_LAWS)}")
        return cls(estimator=estimator, replicates=replicates, prior_width=width, paths=paths, replicate_laws=laws,
                   input=u_id, K0=K0, K1=K1, feedback=feedback, gain=F_id, xi_guess=xi_guess, prior=prior,
                   covariance=covariance, xi_model=xi_model, passes=passes, resamples=resamples, block=block,
                   noise_scales=scales)


@dataclass(frozen=True)
class DesignSettings:
    """conf/gain: the method whose gain the closed loop uses, with its options, and the comparison
    designs (`designs`) for the gains table, each with `options_by_method`. source: identified |
    reported | fixed (a given gain F (m, n))."""

    method: str
    options: dict
    options_by_method: dict
    source: str
    F: np.ndarray | None
    designs: tuple[str, ...] = ()
    lmi_max_n: int | None = None          # LMI designs on larger systems are not_applicable
    fallback: str | None = None           # the loop's method when its own is not_applicable

    @property
    def methods(self) -> list[str]:
        """What a run designs: the loop's method and the comparison designs, in METHODS order."""
        return [m for m in METHODS if m == self.method or m in self.designs]

    @classmethod
    def from_config(cls, cfg, model: AffineRandomSystem, reported) -> DesignSettings:
        method, options = _method_and_options(cfg, "gain")
        with key("gain.options"):
            check_options(method, {k: v for k, v in options.items() if not (k == "poles" and v is None)}, model)
        poles = plain(OmegaConf.select(cfg, "plant.poles"))
        if poles is not None:
            with key("plant.poles"):
                check_options("pole_placement", {"poles": poles}, model)
        # the comparison designs with their default options; pole placement only with poles from the config
        by_method = {m: {} for m in METHODS} | {"pole_placement": {"poles": poles}, method: options}
        source, F = _gain_source(cfg, model, reported)
        designs = plain(OmegaConf.select(cfg, "gain.designs", default=[]))
        designs = list(METHODS) if designs == "all" else designs
        if not isinstance(designs, list) or any(d not in METHODS for d in designs):
            raise ConfigError(f"gain.designs: {designs!r} is not allowed, expected all or a list of "
                              f"{', '.join(METHODS)}")
        lmi_max_n = OmegaConf.select(cfg, "gain.lmi_max_n", default=None)
        lmi_max_n = None if lmi_max_n is None else _number(lmi_max_n, "gain.lmi_max_n", integer=True, low=1)
        fallback = OmegaConf.select(cfg, "gain.fallback", default=None)
        if fallback is not None and fallback not in METHODS:
            raise ConfigError(f"gain.fallback: {fallback!r} is not allowed, expected null or one of "
                              f"{', '.join(METHODS)}")
        return cls(method=method, options=options, options_by_method=by_method, source=source, F=F,
                   designs=tuple(designs), lmi_max_n=lmi_max_n, fallback=fallback)


@dataclass(frozen=True)
class LoopSettings:
    """conf/closed_loop: the Monte Carlo of the closed (and open) loop: P paths over k = 0..K, the
    input disturbance d (K + 1, m) and whether the EnKF is told it, the rate window (None: auto,
    placed on the ideal loop's exact curve above the noise floor), the paths of the loop at rest that
    measures the noise floor (0: not measured), chunks of paths (None: from a memory budget) and
    worker processes."""

    paths: int                            # fixed, or with max_paths the pilot (the first look) of auto
    disturbance: np.ndarray
    filter_sees_disturbance: bool
    open_loop: bool
    rate_window: tuple[int, int] | None
    floor_paths: int
    observer_xi: str
    estimate: str                         # the feedback's estimate: predicted x_{k|k-1} | filtered x_{k|k}
    chunk_paths: int | None
    workers: int
    max_paths: int | None = None          # closed_loop.paths auto: the budget of its looks (None: fixed paths)

    @property
    def horizon(self) -> int:
        return self.disturbance.shape[0] - 1

    @property
    def looks(self) -> tuple[int, ...]:
        """The path counts at which the loops are judged: (paths,) when fixed; auto: the pilot, then LOOK_GROWTH
        times the previous count, the last one max_paths (`pipeline.loops.run_loops`)."""
        if self.max_paths is None:
            return (self.paths,)
        looks = [self.paths]
        while looks[-1] < self.max_paths:
            looks.append(min(LOOK_GROWTH * looks[-1], self.max_paths))
        if len(looks) > 1 and looks[-1] - looks[-2] < looks[-2] // 2:      # no look of a few more paths
            looks.pop(-2)
        return tuple(looks)

    @classmethod
    def from_config(cls, cfg, model: AffineRandomSystem, plant: AffineRandomSystem) -> LoopSettings:
        paths, max_paths = get(cfg, "closed_loop.paths"), None
        if paths == "auto":                 # looks from a pilot up to a budget (pipeline.loops.run_loops)
            paths = _number(get(cfg, "closed_loop.pilot_paths"), "closed_loop.pilot_paths", integer=True, low=2)
            max_paths = _number(get(cfg, "closed_loop.max_paths"), "closed_loop.max_paths", integer=True, low=paths)
        elif isinstance(paths, str):
            raise ConfigError(f"closed_loop.paths: {paths!r} is not allowed, expected auto or an integer >= 1")
        else:
            paths = _number(paths, "closed_loop.paths", integer=True, low=1)
        K = _number(get(cfg, "closed_loop.horizon"), "closed_loop.horizon", integer=True, low=1)
        amplitude = get(cfg, "closed_loop.disturbance.amplitude")
        if isinstance(amplitude, list):                     # one amplitude per input channel
            if len(amplitude) != model.m:
                raise ConfigError(f"closed_loop.disturbance.amplitude: {amplitude!r} is not allowed, expected a "
                                  f"number or m = {model.m} numbers")
            amplitude = [_number(a, "closed_loop.disturbance.amplitude") for a in amplitude]
        else:
            amplitude = _number(amplitude, "closed_loop.disturbance.amplitude")
        until = _number(get(cfg, "closed_loop.disturbance.until"), "closed_loop.disturbance.until", integer=True,
                        low=0)
        d = np.zeros((K + 1, model.m))
        d[:until] = amplitude
        window = _rate_window(get(cfg, "closed_loop.rate_window"), K)
        floor_paths = _number(get(cfg, "closed_loop.floor_paths"), "closed_loop.floor_paths", integer=True, low=0)
        observer_xi = get(cfg, "closed_loop.observer_xi")
        if observer_xi not in OBSERVER_XI:
            raise ConfigError(f"closed_loop.observer_xi: {observer_xi!r} is not allowed, expected one of "
                              f"{', '.join(OBSERVER_XI)}")
        estimate = get(cfg, "closed_loop.estimate")
        if estimate == "auto":              # x_{k|k} whenever y_k does not depend on u_k
            estimate = "filtered" if not (plant.D.any() or model.D.any()) else "predicted"
        if estimate not in ESTIMATES:
            raise ConfigError(f"closed_loop.estimate: {estimate!r} is not allowed, expected auto or one of "
                              f"{', '.join(ESTIMATES)}")
        try:
            check_estimate(plant, model, estimate)
        except ValueError as err:                               # "estimate: ..." -> "closed_loop.estimate: ..."
            raise ConfigError(f"closed_loop.{err}") from None
        flags = {name: _flag(cfg, f"closed_loop.{name}") for name in ("filter_sees_disturbance", "open_loop")}
        chunk = get(cfg, "closed_loop.chunk_paths")
        chunk = None if chunk is None else _number(chunk, "closed_loop.chunk_paths", integer=True, low=1)
        workers = _number(get(cfg, "closed_loop.workers"), "closed_loop.workers", integer=True, low=1)
        return cls(paths=paths, disturbance=d, rate_window=window, floor_paths=floor_paths, observer_xi=observer_xi,
                   estimate=estimate, chunk_paths=chunk, workers=workers, max_paths=max_paths, **flags)


@dataclass(frozen=True)
class TrackingSettings:
    """conf/tracking: what a run records: level off | summary | full (every ensemble member), the
    Rerun recording (never with level off), how many paths of each loop it shows, and the static figure."""

    level: str
    recording: bool
    recorded_paths: int
    figure: bool = True                   # figure.png beside the tables (`experiment.figure`)

    @classmethod
    def from_config(cls, cfg) -> TrackingSettings:
        recording = _flag(cfg, "tracking.recording")
        recorded_paths = _number(get(cfg, "tracking.recorded_paths"), "tracking.recorded_paths", integer=True, low=0)
        level = get(cfg, "tracking.level")
        if level not in TRACKING_LEVELS:
            raise ConfigError(f"tracking.level: {level!r} is not allowed, expected one of "
                              f"{', '.join(TRACKING_LEVELS)}")
        figure = _flag(cfg, "tracking.figure")
        return cls(level=level, recording=recording and level != "off", recorded_paths=recorded_paths,
                   figure=figure and level != "off")


@dataclass(frozen=True)
class ControllerSettings:
    """conf/controller: offline (the paper's two phases) or online (learning-type, run beside the
    offline loop), with the online controller's settings and initial gain (zero | nominal | (m, n))."""

    kind: str = "offline"
    online: OnlineSettings | None = None
    initial: str | np.ndarray = "zero"
    disturbance: np.ndarray | None = None   # Q_d of the online loop's unknown-input estimate (None: enkf.disturbance)

    @classmethod
    def from_config(cls, cfg, model: AffineRandomSystem, loop: LoopSettings) -> ControllerSettings:
        return cls(*_controller(cfg, model, loop))


@dataclass(frozen=True)
class Experiment:
    """Everything a run needs, validated: the plant and the model, and one settings object per
    config group."""

    plant: AffineRandomSystem
    model: AffineRandomSystem
    plant_name: str
    model_name: str                       # "plant's own structure": the plant's own, its xi the plant's
    reported: MomentModel | None          # moments of xi a paper reports for the model, if any
    reference: dict | None                # numbers a paper reports for this plant (summary only)
    q0: np.ndarray                        # (n,) plant initial state
    seed: int
    filter: FilterSettings
    identification: IdentificationSettings
    design: DesignSettings
    loop: LoopSettings
    tracking: TrackingSettings
    controller: ControllerSettings
    data: DataSettings | None = None      # a data run: recorded (u, y) in place of the plant (plant None)


@dataclass(frozen=True)
class DataSettings:
    """conf `data`: the recorded data a data run identifies from (`data.RecordedData`, checked) and the
    fraction of its paths held out for validation (the last `holdout_paths` by path id)."""

    data: RecordedData
    holdout: float
    loops: bool = False        # data.loops: the closed and open loops simulated on the identified model
    prior: AffineRandomSystem | None = None     # the model with its prior guess's law (`model_prior`): the structure
                                                # the model file states (a two-point link), never a truth

    @property
    def holdout_paths(self) -> int:
        P = self.data.recorded.paths
        return min(P - 1, int(math.ceil(self.holdout * P))) if self.holdout > 0 else 0

    @property
    def identification(self) -> Recorded:
        """The recorded paths the identification uses (all but the held-out ones)."""
        return self.data.recorded.select(slice(0, self.data.recorded.paths - self.holdout_paths))

    @property
    def holdout_data(self) -> Recorded | None:
        h = self.holdout_paths
        return self.data.recorded.select(slice(self.data.recorded.paths - h, None)) if h else None


def data_file(cfg) -> str | None:
    """data.file as an absolute path (relative to the directory rdsexp was started in), or None."""
    value = plain(OmegaConf.select(cfg, "data.file"))
    if value is None:
        return None
    if not isinstance(value, str) or not value:
        raise ConfigError(f"data.file: {value!r} is not allowed, expected null or a file name")
    try:
        from hydra.utils import to_absolute_path
        return to_absolute_path(value)
    except (ValueError, ImportError):
        return str(Path(value).resolve())


def model_prior(cfg, model: AffineRandomSystem) -> AffineRandomSystem:
    """A data run's stand-in for the plant while settings are built: the model with the prior guess of
    its xi (model.xi, in the plant-file schema; None without one): the initial ensemble's xi, the EnKF's
    support box and a nominal guess come from it. Nothing is simulated on it."""
    spec = plain(OmegaConf.select(cfg, "model.xi"))
    dist = None
    if spec is not None:
        with key("model.xi"):
            dist = from_spec(spec)
    with key("model.xi"):
        return AffineRandomSystem(model.A, model.B, model.C, model.D, xi_dist=dist)


# every key a plant file may hold (conf/plant/*.yaml; README "Your own system"); any other is a typo
PLANT_KEYS = ("name", "A", "B", "C", "D", "xi", "q0", "poles", "reference", "model", "designs", "rate_window",
              "identification_feedback", "identification_covariance", "identification_xi", "initial_xi",
              "identification_estimator", "filter_sees_disturbance", "observer_xi", "loop_estimate", "nominal",
              "loop_paths", "identification_paths")


def check_plant_keys(cfg) -> None:
    """A plant file's unknown top-level key is a one-line ConfigError naming the file, the key and the closest
    valid key (a misspelled C would otherwise fall back to the identity)."""
    import difflib
    plant = plain(OmegaConf.select(cfg, "plant"))
    for name in plant if isinstance(plant, dict) else ():
        if name not in PLANT_KEYS:
            guess = difflib.get_close_matches(name, PLANT_KEYS, n=1, cutoff=0.5) or \
                [k for k in PLANT_KEYS if k.lower() == name.lower()[:len(k)]][:1]
            hint = f"did you mean {guess[0]}?" if guess else "valid keys: " + ", ".join(PLANT_KEYS)
            raise ConfigError(f"{plant_source()}: unknown key {name}; {hint}")


def plant_source() -> str:
    """The plant file this run composed (DIR/plant/NAME.yaml), as far as Hydra tells; else plant NAME."""
    try:
        from hydra.core.hydra_config import HydraConfig
        runtime = HydraConfig.get().runtime
    except (ValueError, ImportError):
        return "the plant file"
    choice = runtime.choices.get("plant")
    for source in runtime.config_sources:
        if source.schema == "file":
            path = Path(source.path) / "plant" / f"{choice}.yaml"
            if path.is_file():
                return str(path)
    return f"plant/{choice}.yaml"


def build(cfg) -> Experiment:
    """Validate the composed job config `cfg` (without the hydra node) and build the Experiment."""
    check_plant_keys(cfg)
    seed = _number(get(cfg, "seed"), "seed", integer=True, low=0)
    if data_file(cfg) is not None:
        return build_data_run(cfg, seed)
    xi = get(cfg, "plant.xi")
    with key("plant.xi"):
        xi_dist = from_spec(xi)      # {family: normal (default) | uniform | bernoulli | discrete, ...}
    plant = system_from(cfg, "plant", xi_dist)
    plant_name = str(plain(OmegaConf.select(cfg, "plant.name")) or "plant")
    # the model: a model group with bases (model=paper), else bases inline in the plant file
    # (plant.model), else the plant's own affine structure with the plant's xi as the unknown
    reported = None
    if OmegaConf.select(cfg, "model.A") is not None:
        model, model_name = system_from(cfg, "model"), str(plain(OmegaConf.select(cfg, "model.name")) or "model")
        reported = plain(OmegaConf.select(cfg, "model.reported"))
    elif OmegaConf.select(cfg, "plant.model") is not None:
        model, model_name = system_from(cfg, "plant.model"), "inline in the plant file"
    else:
        model, model_name = AffineRandomSystem(plant.A, plant.B, plant.C, plant.D), "plant's own structure"
    if reported is not None:
        if not isinstance(reported, dict) or set(reported) != {"mean", "cov"}:
            raise ConfigError(f"model.reported: {reported!r} is not allowed, expected null or {{mean, cov}}")
        with key("model.reported"):
            reported = model.check_distribution(MomentModel(mean=reported["mean"], cov=reported["cov"]))
    if (plant.n, plant.m, plant.ny) != (model.n, model.m, model.ny):
        raise ConfigError(f"model: (n, m, ny) = {(model.n, model.m, model.ny)} does not match the plant's "
                          f"{(plant.n, plant.m, plant.ny)}")
    q0 = plain(OmegaConf.select(cfg, "plant.q0"))
    with key("plant.q0"):
        q0 = np.ones(plant.n) if q0 is None else np.asarray(q0, dtype=float)      # default: ones (the paper's)
        if q0.shape != (plant.n,) or not np.all(np.isfinite(q0)):
            raise ValueError(f"{plain(OmegaConf.select(cfg, 'plant.q0'))!r} is not allowed, expected null or "
                             f"{plant.n} finite numbers")
    reference = plain(OmegaConf.select(cfg, "plant.reference"))
    if reference is not None and not isinstance(reference, dict):
        raise ConfigError(f"plant.reference: {reference!r} is not allowed, expected null or a mapping")

    return Experiment(plant=plant, model=model, plant_name=plant_name, model_name=model_name, reported=reported,
                      reference=reference, q0=q0, seed=seed, **group_settings(cfg, model, plant, reported))


def group_settings(cfg, model: AffineRandomSystem, plant: AffineRandomSystem, reported, data_run: bool = False) -> dict:
    """One validated settings object per config group (Experiment's fields filter, identification, design, loop,
    tracking, controller); `plant`: the plant, or a data run's prior (the model with its xi as the guess)."""
    check_objective(cfg)           # in this order: a config's first error is the one reported
    identification = IdentificationSettings.from_config(cfg, plant, data_run)
    filter_ = FilterSettings.from_config(cfg, model, plant, identification.xi_guess)
    design = DesignSettings.from_config(cfg, model, reported)
    loop = LoopSettings.from_config(cfg, model, plant)
    return {"identification": identification, "filter": filter_, "design": design, "loop": loop,
            "tracking": TrackingSettings.from_config(cfg),
            "controller": ControllerSettings.from_config(cfg, model, loop)}


def build_data_run(cfg, seed: int) -> Experiment:
    """A data run's Experiment: the model group's structure (model=NAME) with its xi as the prior guess,
    the recorded data checked against it (`data.load`: one line per defect, before any compute), no plant.
    The plant group's system is not used; its settings lines (identification_xi, identification_covariance,
    initial_xi, ...: the paper's plant file's method) still set the identification's method."""
    if OmegaConf.select(cfg, "model.A") is None:
        raise ConfigError("model: a data run needs a model with bases (model=NAME, a file of the model group with "
                          "A, B, C, D), not the plant's own structure")
    model, model_name = system_from(cfg, "model"), str(plain(OmegaConf.select(cfg, "model.name")) or "model")
    reported = plain(OmegaConf.select(cfg, "model.reported"))
    if reported is not None:
        with key("model.reported"):
            reported = model.check_distribution(MomentModel(mean=reported["mean"], cov=reported["cov"]))
    prior = model_prior(cfg, model)
    holdout = _number(get(cfg, "data.holdout"), "data.holdout", low=0, high=0.9)
    groups = group_settings(cfg, model, prior, reported, data_run=True)
    if groups["controller"].kind == "online":
        raise ConfigError("controller: 'online' is not allowed in a data run (there is no plant to run it on)")
    if groups["design"].source == "reported" and reported is None:
        raise ConfigError("gain.source: 'reported' needs model.reported")
    K0, K1 = groups["identification"].K0, groups["identification"].K1
    recorded = load_data(data_file(cfg), model.m, model.ny, K0 + K1 + 1)
    data = DataSettings(recorded, holdout, _flag(cfg, "data.loops"), prior)
    if data.identification.paths < 1:
        raise ConfigError(f"data.holdout: {holdout!r} leaves no recorded path for the identification")
    return Experiment(plant=None, model=model, plant_name="none (recorded data)", model_name=model_name,
                      reported=reported, reference=None, q0=np.zeros(model.n), seed=seed, data=data, **groups)


def check_objective(cfg) -> None:
    """`objective` is null or a metric the registry declares an objective (`metrics.objectives`);
    `objective_penalty` a finite number >= 0; `objective_seeds` a whole number >= 1."""
    objective = OmegaConf.select(cfg, "objective")
    if objective is not None and objective not in objectives():
        raise ConfigError(f"objective: {objective!r} is not allowed, expected null or one of {', '.join(objectives())}")
    _number(OmegaConf.select(cfg, "objective_penalty", default=1.0), "objective_penalty", low=0)
    seeds = OmegaConf.select(cfg, "objective_seeds", default=1)
    if isinstance(seeds, bool) or not isinstance(seeds, int) or seeds < 1:
        raise ConfigError(f"objective_seeds: {seeds!r} is not allowed, expected a whole number >= 1")


def _method_and_options(cfg, group: str) -> tuple[str, dict]:
    """GROUP.method (a synthesis method) and GROUP.options (a mapping, checked by the method later)."""
    method = get(cfg, f"{group}.method")
    if method not in METHODS:
        raise ConfigError(f"{group}.method: {method!r} is not allowed, expected one of {', '.join(METHODS)}")
    options = get(cfg, f"{group}.options") or {}
    if not isinstance(options, dict):
        raise ConfigError(f"{group}.options: {options!r} is not allowed, expected a mapping")
    return method, options


def _flag(cfg, name: str) -> bool:
    value = get(cfg, name)
    if not isinstance(value, bool):
        raise ConfigError(f"{name}: {value!r} is not allowed, expected true or false")
    return value


CONTROLLERS = ("offline", "online")
ONLINE_KEYS = {"type", "initial", "warmup", "period", "memory", "window", "forgetting", "method", "options",
               "safeguard", "resamples", "block", "min_blocks", "covariance", "disturbance", "observer", "start",
               "start_spread", "mean_spread", "lag", "probe", "probe_until"}


def _controller(cfg, model: AffineRandomSystem, loop: LoopSettings) -> tuple[
        str, OnlineSettings | None, str | np.ndarray, np.ndarray | None]:
    """controller.type (offline | online; default offline), the online controller's settings, its initial
    gain and the covariance of its loop's unknown-input estimate (controller.disturbance, None: off)."""
    K = loop.horizon
    node = plain(OmegaConf.select(cfg, "controller")) or {"type": "offline"}
    kind = node.get("type", "offline") if isinstance(node, dict) else node
    if kind not in CONTROLLERS:
        raise ConfigError(f"controller.type: {kind!r} is not allowed, expected one of {', '.join(CONTROLLERS)}")
    if kind == "offline":
        extra = sorted(set(node) - {"type"}) if isinstance(node, dict) else []
        if extra:                         # e.g. +controller.period=5 without controller=online
            raise ConfigError(f"controller.{extra[0]}: not read by controller=offline (the online controller's "
                              f"settings need controller=online)")
        return kind, None, "zero", None
    extra = sorted(set(node) - ONLINE_KEYS)
    if extra:
        raise ConfigError(f"controller: {extra!r} is not allowed, expected keys among {', '.join(sorted(ONLINE_KEYS))}")
    ints = {name: _number(get(cfg, f"controller.{name}"), f"controller.{name}", integer=True, low=low)
            for name, low in (("warmup", 0), ("period", 1), ("window", 2), ("resamples", 0), ("block", 1))}
    # keys added later: a controller file (or a stored run's config) without them keeps the former behaviour
    min_blocks = OmegaConf.select(cfg, "controller.min_blocks", default=OnlineSettings.min_blocks)
    ints["min_blocks"] = _number(plain(min_blocks), "controller.min_blocks", integer=True, low=1)
    lag = plain(OmegaConf.select(cfg, "controller.lag", default=OnlineSettings.lag))
    # auto: at least one step, and enough that every component of xi reaches an output (`output_delay`)
    ints["lag"] = max(1, int(output_delay(model).max(initial=0))) if lag == "auto" else \
        _number(lag, "controller.lag", integer=True, low=0)
    memory = get(cfg, "controller.memory")
    if memory not in MEMORIES:
        raise ConfigError(f"controller.memory: {memory!r} is not allowed, expected one of {', '.join(MEMORIES)}")
    if memory == "window" and ints["window"] > K:
        raise ConfigError(f"controller.window: {ints['window']} is not allowed, longer than closed_loop.horizon = {K}")
    forgetting = _number(get(cfg, "controller.forgetting"), "controller.forgetting", low=0, low_open=True, high=1)
    if forgetting == 1:
        raise ConfigError("controller.forgetting: 1 is not allowed, expected a number in (0, 1) (memory=all keeps all)")
    method, options = _method_and_options(cfg, "controller")
    safeguard = get(cfg, "controller.safeguard")
    if not isinstance(safeguard, bool):
        raise ConfigError(f"controller.safeguard: {safeguard!r} is not allowed, expected true or false")
    covariance = get(cfg, "controller.covariance")
    if covariance not in COVARIANCES:
        raise ConfigError(f"controller.covariance: {covariance!r} is not allowed, expected one of "
                          f"{', '.join(COVARIANCES)}")
    observer = plain(OmegaConf.select(cfg, "controller.observer", default="random_walk"))
    if observer not in OBSERVERS:
        raise ConfigError(f"controller.observer: {observer!r} is not allowed, expected one of {', '.join(OBSERVERS)}")
    start = plain(OmegaConf.select(cfg, "controller.start", default=OnlineSettings.start))
    if start not in STARTS:
        raise ConfigError(f"controller.start: {start!r} is not allowed, expected one of {', '.join(STARTS)}")
    start_spread, mean_spread = (
        _number(plain(OmegaConf.select(cfg, f"controller.{name}", default=getattr(OnlineSettings, name))),
                f"controller.{name}", low=0, low_open=True) for name in ("start_spread", "mean_spread"))
    probe = _number(plain(OmegaConf.select(cfg, "controller.probe", default=0.0)), "controller.probe", low=0)
    probe_until = plain(OmegaConf.select(cfg, "controller.probe_until", default="auto"))
    if probe_until == "auto":
        # where the verdict's rate window may start (the configured window's first step, else the first step
        # after the disturbance: `window_start`), so the online loop's empirical rate measures its decay
        probe_until = loop.rate_window[0] if loop.rate_window is not None else window_start(loop.disturbance, model.n)
    elif probe_until is not None and not (isinstance(probe_until, int) and not isinstance(probe_until, bool)
                                          and probe_until >= 0):
        raise ConfigError(f"controller.probe_until: {probe_until!r} is not allowed, expected auto, null or a step >= 0")
    with key("controller.options"):
        settings = OnlineSettings(memory=memory, forgetting=forgetting, method=method, options=options,
                                  covariance=covariance, observer=observer, start=start, start_spread=start_spread,
                                  mean_spread=mean_spread,
                                  safeguard=safeguard, probe=probe, probe_until=probe_until, **ints).check(model, K)
    initial = get(cfg, "controller.initial")
    if isinstance(initial, list):
        with key("controller.initial"):
            initial = model.check_gain(initial)
    elif initial not in ("zero", "nominal"):
        raise ConfigError(f"controller.initial: {initial!r} is not allowed, expected zero, nominal or a gain "
                          f"[[...]] of shape (m, n) = {(model.m, model.n)}")
    disturbance = None
    if OmegaConf.select(cfg, "controller.disturbance", default=None) is not None:
        disturbance = _covariance(cfg, "controller.disturbance", model.m)
        if not disturbance.any():
            raise ConfigError(f"controller.disturbance: {get(cfg, 'controller.disturbance')!r} is not allowed, "
                              f"expected null or a nonzero covariance (a scale, m diagonal entries or m x m)")
    return kind, settings, initial, disturbance


def _process_noise(cfg, n: int, p: int) -> np.ndarray:
    """enkf.Q: {x: scale, xi: scale, matrix: null} -> diag(x I_n, xi I_p); a non-null `matrix` (a
    scalar, n + p diagonal entries or a full (n+p, n+p) matrix) replaces the scales. A conf file may
    also give enkf.Q itself as such a matrix."""
    Q = get(cfg, "enkf.Q")
    if not isinstance(Q, dict):
        return _covariance(cfg, "enkf.Q", n + p)
    if not {"x", "xi"} <= set(Q) <= {"x", "xi", "matrix"}:
        raise ConfigError(f"enkf.Q: {Q!r} is not allowed, expected {{x: scale, xi: scale, matrix: null or a "
                          f"scalar, {n + p} diagonal entries or ({n + p}, {n + p})}}")
    if Q.get("matrix") is not None:
        return _covariance(cfg, "enkf.Q.matrix", n + p)
    scales = [_number(Q[part], f"enkf.Q.{part}", low=0) for part in ("x", "xi")]
    return np.diag(np.repeat(scales, [n, p]))


def _rate_window(window, K: int) -> tuple[int, int] | None:
    """closed_loop.rate_window: auto (None), [k_from, k_to] as steps (integers) or as fractions of the
    horizon K."""
    if window == "auto":
        return None
    if isinstance(window, list) and len(window) == 2 and all(isinstance(k, float) for k in window) \
            and all(0 <= k <= 1 for k in window):
        window = [round(k * K) for k in window]
    if not (isinstance(window, list) and len(window) == 2 and all(isinstance(k, int) for k in window)
            and 0 <= window[0] < window[1] <= K):
        raise ConfigError(f"closed_loop.rate_window: {window!r} is not allowed, expected auto, [k_from, k_to] "
                          f"with 0 <= k_from < k_to <= closed_loop.horizon = {K} (integers), or fractions "
                          f"of the horizon (e.g. [0.6, 0.8])")
    return tuple(window)


def _identification_feedback(cfg, plant: AffineRandomSystem,
                             data_run: bool) -> tuple[str, np.ndarray | None, np.ndarray, str]:
    """identification.feedback (none | nominal | auto | a gain F (m x n)), identification.xi_guess and where it
    comes from (`prior_guess`).

    xi_guess is the nominal guess of the plant's random parameters, in the plant file's xi, that a
    stabilizing gain is designed on and the EnKF starts from: prior knowledge, never the law the plant is
    simulated from unless asked for (`oracle`)."""
    feedback = plain(OmegaConf.select(cfg, "identification.feedback", default="none"))
    F = None
    if isinstance(feedback, list):
        with key("identification.feedback"):
            F = plant.check_gain(feedback)
        feedback = "given"
    elif feedback not in FEEDBACK_MODES:
        raise ConfigError(f"identification.feedback: {feedback!r} is not allowed, expected one of "
                          f"{', '.join(FEEDBACK_MODES)} or a gain [[...]] of shape (m, n) = {(plant.m, plant.n)}")
    xi_guess, prior = prior_guess(cfg, plant, data_run)
    return feedback, F, xi_guess, prior


# where identification.xi_guess comes from (`prior_guess`); only `oracle` reads the law the plant is simulated from
PRIORS = {"given": "identification.xi_guess", "nominal": "the plant file's nominal",
          "zero": "none stated: xi = 0, the plant file's A_0, B_0", "model": "the model's prior (model.xi)",
          "oracle": "ORACLE: the mean of the law the plant is simulated from (not blind)"}


def prior_guess(cfg, plant: AffineRandomSystem, data_run: bool = False) -> tuple[np.ndarray, str]:
    """The prior guess of the plant's xi (p,), in the plant file's xi, and where it comes from (a PRIORS key):
    identification.xi_guess as given (a list), `oracle` (the mean of the plant file's law: what a simulated run
    is judged against, so labelled), or null: the plant file's `nominal:` (what the researcher knows before the
    experiment), else xi = 0 (the nominal system A_0, B_0 the plant file's bases are written around); a data
    run's null is the model's prior (model.xi), else 0. A simulated run reads the law only for `oracle`."""
    guess = plain(OmegaConf.select(cfg, "identification.xi_guess"))
    nominal = None if data_run else plain(OmegaConf.select(cfg, "plant.nominal", default=None))
    name = "identification.xi_guess" if guess is not None or nominal is None else "plant.nominal"
    with key(name):
        if guess == "oracle":
            if data_run or plant.xi_dist is None:
                raise ValueError("'oracle' is not allowed without a plant law to read (a data run has none)")
            return plant.check_distribution(None).mean, "oracle"
        if isinstance(guess, str):
            raise ValueError(f"{guess!r} is not allowed, expected null, oracle or p = {plant.p} finite numbers "
                             "(the plant file's xi)")
        value, source = (guess, "given") if guess is not None else (nominal, "nominal")
        if value is None:
            if data_run and plant.xi_dist is not None:
                return plant.check_distribution(None).mean, "model"
            return np.zeros(plant.p), "zero"
        xi_guess = np.asarray(value, dtype=float)
        if xi_guess.shape != (plant.p,) or not np.all(np.isfinite(xi_guess)):
            raise ValueError(f"{value!r} is not allowed, expected null or p = {plant.p} finite numbers "
                             "(the plant file's xi)" + (", or oracle" if name.startswith("identification") else ""))
    return xi_guess, source


# ------------------------------------------------------------------------- strict overrides
GROUPS = ("plant", "model", "enkf", "identification", "gain", "closed_loop", "tracking")
TOP_LEVEL = ("seed", "reuse", "cache", "objective", "objective_penalty", "data")
# keys `build` reads with a default when the group's file does not set them: `+key=value` may add them
OPTIONAL_KEYS = ("plant.name", "plant.C", "plant.D", "plant.q0", "plant.poles", "plant.reference", "plant.nominal",
                 "plant.identification_feedback", "plant.identification_covariance", "plant.identification_xi",
                 "plant.identification_estimator", "plant.loop_paths", "plant.identification_paths",
                 "plant.rate_window", "plant.filter_sees_disturbance",
                 "plant.observer_xi", "plant.initial_xi", "plant.loop_estimate", "plant.designs", "plant.model",
                 "model.name",
                 "model.A", "model.B", "model.C", "model.D", "model.reported", "gain.source", "gain.F", "gain.options",
                 "identification.feedback", "identification.xi_guess")
# mappings whose keys are checked where they are used (gain options by the method, xi by its family)
FREE_FORM = ("gain.options.", "plant.xi.", "plant.reference.", "plant.model.", "model.reported.")


def _keys(node, prefix: str = "") -> list[str]:
    """Every dotted key of a (nested) mapping."""
    if not isinstance(node, dict):
        return []
    return [k for name, value in node.items() for k in (f"{prefix}{name}", *_keys(value, f"{prefix}{name}."))]


def check_overrides(cfg, overrides) -> None:
    """Reject `+key=value` (and `++key=value`) that adds a key rdsexp does not read inside its groups
    (or at the top level): one line with the closest known key. Hydra itself only refuses `+` on a
    key that exists, so without this a typo (`+enkf.ensemble_sze=50`) would run with the default."""
    import difflib

    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import OverrideType
    try:
        parsed = OverridesParser.create().parse_overrides([str(o) for o in overrides])
    except Exception:         # noqa: BLE001 -- a malformed override is Hydra's own error, reported by Hydra
        return
    for override in parsed:
        name = override.key_or_group
        if override.type not in (OverrideType.ADD, OverrideType.FORCE_ADD) or "@" in name or "/" in name:
            continue
        group = name.split(".")[0]
        if "." not in name and (name in TOP_LEVEL or _is_group(name)):
            continue                     # a config group (+sweep=paper) or a top-level key rdsexp reads
        if "." in name and group not in GROUPS:
            continue                     # outside rdsexp's groups (hydra.*, a user's own group)
        if name in OPTIONAL_KEYS or name.startswith(FREE_FORM):
            continue
        known = sorted({*(k for k in _keys(plain(cfg)) if not (name + ".").startswith(k + ".")
                        and (k.split(".")[0] in GROUPS or k in TOP_LEVEL)), *OPTIONAL_KEYS})
        guess = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
        hint = f", did you mean {guess[0]}?" if guess else f"; keys of {group}: " + ", ".join(
            k for k in known if k.startswith(f"{group}.") and k.count(".") == 1)
        raise ConfigError(f"{name}: unknown key (added with {override.input_line.split('=')[0]}){hint}")


def _is_group(name: str) -> bool:
    """A config group of rdsexp's conf/ (sweep, plant, ...)."""
    from importlib.resources import files
    return (files("rdsexp.conf") / name).is_dir()

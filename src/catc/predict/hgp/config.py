"""The parameters of the HGP (:class:`HgpConfig`) and of the direct HGP
(:class:`HgpDirectConfig`), with the measurements behind each default
(docs/reference/predictors.md).

A configuration checks itself when it is made (``__post_init__``): a bad value fails there,
with a ``ValueError`` that names it, not at the first forecast.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from catc.predict.kinematic_table import KINEMATIC


@dataclass(frozen=True)
class HgpConfig:
    """Every parameter of the HGP; defaults follow the paper where it gives one.  Checked
    when made (``ValueError``): ``reselect_every`` an integer >= 1, ``branch_edges``
    ascending, ``branch_margin`` one number or one per gap class, ``branches`` names of
    :data:`catc.predict.kinematic_table.KINEMATIC`."""

    tw: int = 30  # training window, samples (paper: TW = 30, 3 s)
    # Hyperparameter bounds (γ s, α1, α2) per series, from what a car can do rather than
    # the GP core's generic ones: a speed deviation of at most ~10 m/s and a trend of at
    # most 5 m/s² within a window; a heading deviation of at most ~2 rad and a turn rate
    # of at most 1 rad/s (57°/s).  Without them LOO on short, nearly linear windows drives
    # α1 to 10³ with γ of tens of seconds: a stiff polynomial that extrapolates curvature
    # without limit across long gaps (measured, see the issue note).
    speed_bounds: tuple = ((0.3, 100.0), (1e-3, 10.0), (1e-4, 5.0))
    heading_bounds: tuple = ((0.3, 100.0), (1e-4, 2.0), (1e-5, 1.0))
    min_points: int = 4  # fewer received samples in the window: CA fallback
    horizon_s: float = 10.0  # longest GP forecast; constant speed beyond it
    noise_speed: float = 0.01  # σn² of the speed series, (m/s)²: GNSS speed noise ~0.1 m/s
    noise_heading: float = 3e-5  # σn² of the heading series, rad² (~0.3°)
    accel_max: float = 8.0  # m/s², |dμs/dt| beyond this is implausible
    yaw_rate_max: float = 60.0  # deg/s
    lat_accel_max: float = 8.0  # m/s², μs·|dμh/dt|
    speed_std_max: float = 3.0  # m/s, divergence of the speed forecast
    heading_std_max: float = 25.0  # deg, divergence of the heading forecast
    pte_th: float = 0.5  # m, the paper's PTE_th for creating a model online
    backtest_s: float = 1.0  # s held out at the end of the window for the online check
    online: bool = False  # measured: no gain at 5-10x the cost (see the issue note)
    online_max: int = 32
    integration: str = "trapezoid"  # or "left", the paper's literal recursion
    heading_damping: bool = True  # E[cos h] = exp(−σh²/2)·cos μh (paper); False: cos μh
    # Diagnostics: replace one GP by its kinematic counterpart (needs ``slopes``):
    # speed "ca" = last speed + acceleration·τ; heading "ctrv" = last heading + yaw rate·τ.
    speed_model: str = "gp"
    heading_model: str = "gp"
    window_s: float = math.inf  # also drop samples older than this (s) before the last one
    slopes: bool = True  # condition on the BSM's accel and yaw rate at the last sample
    select_with_slopes: bool = True  # choose bank models by the likelihood of values + slope
    noise_accel: float = 0.005  # (m/s²)², BSM longitudinal acceleration (σ 0.07 m/s²)
    noise_yaw: float = 3e-5  # (rad/s)², BSM yaw rate (σ 0.3 deg/s)
    # Model persistency: the bank selection is redone only every ``reselect_every``
    # received samples and after a gap longer than ``reselect_gap_s`` between two received
    # samples (0.25 s: two or more BSMs lost in a row at 10 Hz); in between the selected θ
    # are reused.  1 and inf select at every sample (the behaviour before).  Measured on
    # both datasets: PTE95 within 1.5 % of that at PER 0-95 %
    # (docs/log/2026-11-22-hgp-model-persistency.md).
    reselect_every: int = 10
    reselect_gap_s: float = 0.25
    # ... unless the GP's forecast over the gap, with the models in use, landed within
    # ``reselect_fit_m`` of the BSM that ends it: the models still fit, as the paper keeps a
    # bank model until it misses by PTE_th.  0: every such gap reselects (the rule before).
    # Chosen by leave-one-trip-out over both datasets (`python bench/hgp_cv.py --a hgp --b
    # fit-0.02,fit-0.05,fit-0.1`, docs/log/2026-12-06-grid-and-fit.md): 2 cm is within
    # 1.2 % of PTE95 at every PER on both and skips 18 % of the selections at PER 50 %
    # (bench/step.py's scene); 5 cm skips 46 % but costs NGSIM 2.4 % at PER 80 %.
    reselect_fit_m: float = 0.02
    # Data-driven hybrid (issue 17; docs/log/2026-11-25-hgp-branches.md): kinematic predictors run
    # beside the GP (names from catc.predict, e.g. ("ca", "kf")).  At every BSM that ends a gap
    # (one or more BSMs lost) each branch's squared position error at that BSM, from what it had
    # forecast over the gap, enters a running score per branch (exponentially weighted,
    # ``branch_decay`` the weight of the old score), one score per gap-length class
    # (``branch_edges``, s: a gap of 0.2 s and one of 5 s are different questions); at ``tau`` s
    # into a gap the branch with the lowest score of tau's class answers, a kinematic one only
    # when its score is below ``branch_margin`` × the GP's; a class without scores yet is answered
    # by the GP.  () is the GP alone (its own switching above still applies).  Measured
    # (bench/hgp_ablation.py, docs/log/2026-11-25-hgp-branches.md): CA and KF with margin 0.5 take
    # 3-14 % off PTE95 at PER 10-50 % on both datasets and add at most 1.7 % at 80-95 %; margin 1
    # gains more at low PER and loses up to 5 % at PER 90 %; adding CTRV changed little.  Shipped:
    # margin 1 for gaps up to 0.35 s and 0.5 for longer ones (per class: a float is every
    # class's), chosen by leave-one-trip-out over both datasets
    # (docs/log/2026-11-26-hgp-blend-and-margin.md).
    branches: tuple = ("ca", "kf")
    branch_decay: float = 0.8
    branch_margin: float | tuple = (1.0, 0.5, 0.5, 0.5)  # or one for every gap class
    branch_edges: tuple = (0.35, 1.05, 3.05)
    # Blend instead of switching (> 0): at tau the answer is the mean of the branches'
    # (the GP's too) whose score in tau's class is at most ``branch_blend`` × the best,
    # weighted by score ** -blend_power (1: inverse-MSE weights); inf: every branch.  Off
    # (0): measured, it trades NGSIM's low and 90 % PER against OpenACC's 80-95 % as the
    # margin does (docs/log/2026-11-26-hgp-blend-and-margin.md).
    branch_blend: float = 0.0
    blend_power: float = 1.0  # weights ∝ score ** -blend_power

    def __post_init__(self) -> None:
        if int(self.reselect_every) != self.reselect_every or self.reselect_every < 1:
            raise ValueError(f"reselect_every must be an integer >= 1, got "
                             f"{self.reselect_every!r}")
        if list(self.branch_edges) != sorted(self.branch_edges):
            raise ValueError(f"branch_edges must be ascending, got {self.branch_edges!r}")
        self.margins()
        unknown = [name for name in self.branches if name not in KINEMATIC]
        if unknown:
            raise ValueError(f"branches must be kinematic predictors "
                             f"({', '.join(KINEMATIC)}), got {unknown[0]!r}")

    def margins(self) -> list[float]:
        """``branch_margin`` for each gap class (ValueError unless one, or one per class)."""
        classes = len(self.branch_edges) + 1
        if isinstance(self.branch_margin, (int, float)):
            return [float(self.branch_margin)] * classes
        if len(self.branch_margin) == classes:
            return [float(m) for m in self.branch_margin]
        raise ValueError(f"branch_margin: one per gap class ({classes}), got "
                         f"{self.branch_margin!r}")


@dataclass(frozen=True)
class HgpDirectConfig:
    """Parameters of the direct HGP; the switching limits mean what they mean for ``hgp``."""

    tw: int = 30
    min_points: int = 4
    horizon_s: float = 10.0
    noise_pos: float = 0.01  # σn² of the x and y series, m² (GNSS noise after smoothing)
    accel_max: float = 8.0  # m/s², from second differences of the mean path
    position_std_max: float = 5.0  # m, divergence
    theta0: tuple[float, float, float] = (2.0, 1.0, 10.0)  # first warm start: γ s, α1 m, α2 m/s
    #: Model persistency, as ``HgpConfig.reselect_every``: θ is re-fitted when at least
    #: this many BSMs arrived since the last fit (1 = at every forecast, as before).  Each
    #: fit is two LOO optimisations (~3 ms each on x/y windows): re-fitting at every BSM
    #: made hgp-d 8× the cost of hgp in a sweep; 10 cuts its cost 3.5× and moves PTE95 both
    #: ways (NGSIM, 30 pairs: +32 % at PER 50 %, −12 % at 90 %; docs/reference/sweeps.md).
    refit_every: int = 10

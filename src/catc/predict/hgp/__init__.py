"""The Hybrid Gaussian Process (HGP) predictor of the reference paper (Valiente et al.,
section "Hybrid-learning-based Gaussian Process (HGP) prediction system").

Indirect HGP (``hgp``): two independent GPs model the RV's speed and (unwrapped)
heading over the last ``tw`` received samples.  For each a model θ = {γ, α1, α2} is
chosen from the kernel bank by maximum log marginal likelihood (paper eq. "model
selection"), the posterior gives mean and variance at 0.1 s steps after the last BSM
(eq. "forecasting heading and speed"), and the position is integrated piecewise with
E[s·cos h] = μs·exp(−σh²/2)·cos μh (eq. "position prediction 2"; here with sine for
east because headings are clockwise from north).  Direct HGP (``hgp-d``) puts the GPs
on x and y instead.

Formulation.  Every choice below was measured on both shared datasets (OpenACC and
NGSIM, all trips, PER 90 % and 95 %, one seed); the numbers are in docs/reference/predictors.md.

* Time relative to the last received sample (t ≤ 0) and each series relative to its last
  received value.  With that origin the linear term α2²·t·t' is a slope prior anchored at
  the last sample and the zero prior mean means "no change since the last BSM".
* The window is the last ``tw`` received samples (the paper's TW), not a time span: capping
  it at 15–60 s changed PTE95 by under 4 %, and at 3–10 s it made it worse.
* Slopes (our addition; ``slopes``): each GP is also conditioned on the derivative the
  BSM itself carries at the last sample, the longitudinal acceleration for speed and the
  yaw rate for heading (a derivative observation, R&W 2006 §9.4; the kernel and θ are
  unchanged).  The kinematic baselines use these fields and the paper's HGP did not; at
  PER 90 % the history is sparse and without them the GP learns a turn or a braking only
  seconds late.  Bank models are then chosen by the likelihood of values and slope
  together (``select_with_slopes``).
* Hyperparameter bounds per series from vehicle physics (``speed_bounds``,
  ``heading_bounds``), used by training and by online fits.

Hybrid switching (paper: "GP predictions are swapped with constant speed and constant
acceleration predictions if a specific criterion is met").  The forecast is walked in
0.1 s steps; at the first step where any criterion below holds, the GP is abandoned
for the rest of the gap:

* negative speed (μs < 0): the vehicle is stopping; it stops there (CA with the stop
  rule: speed 0 from then on), source ``"ca"``;
* |dμs/dt| > ``accel_max`` (longitudinal acceleration beyond what a car does), or
* |dμh/dt| > ``yaw_rate_max``, or lateral acceleration μs·|dμh/dt| > ``lat_accel_max``, or
* divergence: σs > ``speed_std_max`` or σh > ``heading_std_max``:
  constant speed and heading from the last plausible GP state, source ``"cs"``.

Online models (paper: "If there is no model in the reduced kernel bank that meets the
required PTE_th a new model is created, added to the bank, and selected"): when a
forecast is first needed after a BSM, the selected models are back-tested on the
window (condition on all but the last ``backtest_s`` seconds, forecast those, compare
integrated positions with the received ones).  If the error exceeds ``pte_th``, new
speed and heading models are fitted by LOO-CV on the window (warm-started from the
selected ones) and added to this predictor's online bank, bounded to ``online_max``
models (oldest dropped first).  Off by default (``online``): with the shipped bank it
changed PTE95 by under 4 % either way at 5–10 times the cost (docs/reference/predictors.md).

Model persistency (paper: a selected model stays the best for many samples): the bank
selection is reused for up to ``reselect_every`` = 10 received BSMs and redone sooner after
a gap of more than ``reselect_gap_s`` = 0.25 s (two or more BSMs lost in a row).  Measured
on both datasets at PER 0–95 %: PTE95 within 1.5 % of selecting at every BSM, at about a
quarter of the selections at PER 50 % (docs/log/2026-11-22-hgp-model-persistency.md).

Cost.  An OBU makes one forecast per RV and received BSM; at 31 × 31 a LAPACK call from
Python is mostly call overhead, not arithmetic.  The readable formulas (:mod:`.reference`
and :meth:`HgpPredictor._make_forecast_reference`) are the reference the tests hold the
fast path to (1e-9 m over 3 s): the window kept as running arrays; the
exponentials of every window and model by numpy in one pass, and the Cholesky
factorisations, solves and likelihoods of all of them in compiled kernels that factor many
systems side by side (:mod:`catc.predict.gpkernels`, numba); cached posterior weights for
loss-free windows; one cumsum for positions and variances; and :func:`forecast_many`,
which stacks all of it over the predictors due at a tick.

Layout.  One module per part of the method, in the order a forecast uses them; each
imports only those above it (no cycle; none imports :mod:`catc.predict` back):

==============  ==========================================================================
config          :class:`HgpConfig`, :class:`HgpDirectConfig`, checked when made
reference       the readable formulas: slope-conditioned posterior and likelihood, the
                regular-grid banks, :func:`forecast_path`, the switching criteria
gpstack         the same GP arithmetic stacked over models and windows (fast path)
window          the received window: :class:`WindowPredictor` (both predictors) and
                ``WindowState``, the explicit state the fast path works on
selection       bank model selection, readable and stacked
online          online models: back-test and LOO fit
stacked         the fast path: the forecasts of many windows in one set of calls
branches        the kinematic branches beside the GP and their scores
predictor       :class:`HgpPredictor`, :func:`forecast_many_at` (its batch preparer)
table           :class:`~.table.HgpTable`: many RVs' HGP predictors as rows of shared
                arrays, the same answers (the CA-TC's, issue 30)
direct          :class:`HgpDirectPredictor`
==============  ==========================================================================

Why this shape: the reference formulas and the fast path are kept apart so that the tests
can hold one to the other; the fast path takes an explicit ``WindowState`` (the predictor
hands it over) instead of reading the predictor's fields, so the predictor is only the
answering logic.  The submodules are importable (tests and benches use
:mod:`.reference`, :mod:`.gpstack` and :mod:`.stacked` directly); what other packages use
is re-exported here.
"""

from catc.predict.forecast import integrate
from catc.predict.hgp.config import HgpConfig, HgpDirectConfig
from catc.predict.hgp.direct import HgpDirectPredictor
from catc.predict.hgp.predictor import HgpPredictor, forecast_many, forecast_many_at
from catc.predict.hgp.reference import (
    RegularSlopeBank,
    RegularSlopePosterior,
    forecast_path,
    lml_with_slope,
    posterior_with_slope,
)

__all__ = ["HgpConfig", "HgpDirectConfig", "HgpDirectPredictor", "HgpPredictor",
           "RegularSlopeBank", "RegularSlopePosterior", "forecast_many", "forecast_many_at",
           "forecast_path", "integrate", "lml_with_slope", "posterior_with_slope"]

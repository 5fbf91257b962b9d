"""Every tuning constant of the estimators: named, defaulted, justified, overridable.

Rates are given per second (``lambda_*`` are the per-second forgetting factors; the per-tick value
is ``lambda ** dt``), so the same tuning works from 0.01 s to 10 s sample periods.
"""

from __future__ import annotations

from typing import Literal, Self

from pydantic import BaseModel, ConfigDict, Field, model_validator

from bmsid.estimate.observer_tuning import ObserverTuning

Variant = Literal["non-hy-affrls", "hy-affrls", "hy-affrls-lpso"]
VARIANTS_T: tuple[Variant, ...] = ("non-hy-affrls", "hy-affrls", "hy-affrls-lpso")


class EstimatorTuning(BaseModel):
    """Tuning of AFFRLS (Eq. 16-21), LPSO (Eq. 24-30) and their fusion."""

    # strict: part of the daemon TOML, where a quoted number is refused, not coerced
    model_config = ConfigDict(
        extra="forbid", frozen=True, strict=True, use_attribute_docstrings=True
    )

    # --- identification rate -------------------------------------------------------------
    id_period_s: float = Field(1.0, gt=0.0, le=10.0)
    """Samples are averaged into bins of this length before identification. 1 s resolves the
    fast branch of most cells (tau1 >= a few s) and keeps the slow pole (minutes) within reach
    of a 5-parameter model; CAN rates of 10-100 Hz add only noise averaging. SOC and the
    hysteresis state still follow every raw sample (Eq. 2, 5-6: h moves with |i|, which a
    bin's mean loses where charge and discharge alternate within it)."""
    gap_s: float = Field(30.0, gt=0.0)
    """A jump in time longer than this is a gap: the states are propagated at zero current and
    the regression history restarts (we cannot know what the current was)."""

    # --- AFFRLS, Eq. 21 -----------------------------------------------------------------
    lambda_min: float = Field(0.98, gt=0.5, lt=1.0)
    """Per-second floor of the forgetting factor: a memory of ~50 s after a surprise, short
    enough to re-converge after a parameter jump, long enough to average 1 mV noise."""
    lambda_max: float = Field(0.999, gt=0.5, le=1.0)
    """Per-second ceiling: ~1000 s memory in steady operation. Eq. 21 as printed goes to 1,
    which freezes the estimate (no tracking of ageing or temperature): we stop just below."""
    forgetting_base: float = Field(0.5, gt=0.0, lt=1.0)
    """The base (the paper's h) of lambda = lmin + (lmax - lmin) base^eps, eps = (e/e_base)^2."""
    e_base_sigmas: float = Field(3.0, gt=0.0)
    """e_base = this many running RMS innovations: a 3-sigma surprise halves lambda's margin."""
    e_floor_V: float = Field(0.5e-3, gt=0.0)
    """Lower bound of e_base and of the innovation scale, V (ADC resolution order)."""
    innovation_scale_s: float = Field(300.0, gt=0.0)
    """Time constant of the running innovation RMS, s."""
    innovation_clip_sigmas: float = Field(6.0, gt=1.0)
    """Innovations beyond this many RMS are clipped before the update (spikes, glitches)."""
    p0: float = Field(1.0e4, gt=0.0)
    """Initial covariance in normalised units (parameters scaled by their start values)."""
    trace_max: float = Field(1.0e5, gt=0.0)
    """Bound on trace(P) in normalised units: stops wind-up under poor excitation."""
    rest_current_C: float = Field(0.01, ge=0.0)
    """Below this |I| (in C-rate) with no current change, forgetting is switched off (lambda = 1):
    a resting cell carries no new information about R0 and P must not grow."""
    excitation_C: float = Field(0.02, ge=0.0)
    """RMS current variation (C-rate) over ``excitation_window_s`` below which an estimate is
    flagged poorly excited."""
    excitation_window_s: float = Field(300.0, gt=0.0)
    """Time constant of the running current variance that measures excitation, s. After a
    single step (a charge starting) the cell counts as excited for ~2 x this x ln(step /
    limit): 28 min for a C/3 charge. 60 s was measured (3-day ``bench/multiday.py``): clean
    R0+R1+R2 day 3 8.6 -> 1.3 %, tau1 13.7 -> 1.1 %, but ``after-charge`` 4.1 -> 12.6 %,
    ``all`` 2.5 -> 16 % and A123 DYN50 3.68 -> 4.21 mV: not the default."""

    # --- fusion ------------------------------------------------------------------------
    identify_ocv_offset: bool = False
    """Refit an OCV offset (V) with each swarm window: absorbs OCV-curve error, temperature and
    coulomb-counting drift on real cells, at the price of a less certain slow branch (R2, tau2):
    under a steady mean current the two are nearly collinear. Off by default; turn it on for
    cells whose OCV curve is uncertain (rest-point tables, far from the OCV test temperature)."""
    ocv_offset_prior_V: float = Field(0.01, gt=0.0)
    """Prior std of the OCV offset, V. Under a steady mean current the offset and the slow
    branch (R2 x2) are nearly collinear; this prior decides that direction, the data the rest."""
    knee_slope_factor: float = Field(10.0, gt=0.0)
    """Parameters are not learnt where |dOCV/dz| exceeds this many times its median over
    20-80 % SOC: in the OCV curve's knees (below ~10 %, and above ~90 % on LFP) a SOC error of
    a point is tens of mV of OCV error, which the estimators would learn as resistance (R2
    driven to its bound in every low-SOC tail). The model keeps running there with what was
    learnt before; ``inf`` learns everywhere."""
    identify_hysteresis_scale: bool | None = None
    """Identify a scale on the M(z) half-gap (Eq. 32) with the resistances, every tick and in
    each swarm window. ``None`` (default): only when the SOC observer does not learn M
    (``observer.enabled`` and ``observer.learn_hysteresis``), as the paper's method with a plain
    count. Under load h sits at +-1 for minutes, so a scale on h M(z) is a level the fits share
    with the slow branch (R2) and any SOC error: on the multi-day records (``bench/multiday.py``,
    3 days) it cost R0+R1+R2 up to 24 % where M was known; with M learnt at rests instead,
    8.6 % at most from day 2. With a plain count it also absorbs SOC drift (A123 DYN50, the
    observer off: 9.2 mV with it, 15.2 without)."""

    observer: ObserverTuning = ObserverTuning()
    """The SOC observer: SOC, the current-sensor offset and capacity from the voltage."""

    # --- LPSO, Eq. 24-30 ---------------------------------------------------------------
    window_s: float = Field(1800.0, gt=0.0)
    """Sliding window the swarm fits, s: 30 min holds several DST/bus cycles and 3 slow tau."""
    min_window_s: float = Field(300.0, gt=0.0)
    """First swarm once this much excited data is buffered."""
    swarm_min_steps: int = Field(4, ge=0)
    """A swarm starts only when the window holds this many current changes of at least
    ``excitation_C``: two pulses, whose step responses and the relaxation between them tie the
    time constants down; a constant-current charge has one, whose step response cannot be told
    from the hysteresis swing and the OCV slope that follow it. A drive has hundreds, an HPPC
    test's 30-minute window 4 at most: at 10 (before) the swarm never ran on HPPC and tau1,
    tau2 stayed at their start values (known-truth HPPC: RMSE 3.49 -> 1.54 mV at 4; the
    synthetic, measured, physics-based and 3-day tables unchanged)."""
    swarm_reject_ratio: float = Field(2.0, gt=1.0)
    """A finished swarm is not applied when its result, as applied (linear part clipped to the
    bounds), fits the window more than this many times worse (RMS) than the parameters in
    force. The swarm ranks candidates on the window it was started with and the result is
    judged on the window at its end, so up to ~1.5x happens with good results (A123 DYN50:
    0.67-1.6x, one 4.5x); a wrong optimum is far worse."""
    swarm_rls_restart: bool = True
    """After each applied swarm the RLS restarts: P back to ``p0`` for all but R0, which keeps
    its window variance (``affrls.swarm_covariance``). False: the RLS carries the window fit's
    covariance, as before issue 11 (CALCE 0 degC DST 9.48 mV instead of 6.53)."""
    swarm_period_s: float = Field(600.0, gt=0.0)
    """A swarm starts every this many seconds per cell (cells of a bank are staggered)."""
    n_particles: int = Field(12, ge=4, le=200)
    """Particles per swarm (each one a candidate pair tau1, tau2)."""
    n_iter: int = Field(10, ge=2, le=500)
    """Iterations of a warm-started swarm (iter_max of Eq. 29)."""
    n_iter_first: int = Field(20, ge=2, le=1000)
    """Iterations of the first (cold) swarm; later swarms start from the previous optimum."""
    fits_per_update: int = Field(4, ge=1)
    """Window fits (one particle each) per ``update`` call and running swarm: the real-time
    budget. One fit of an 1800-sample window costs ~0.3-1 ms; a swarm iteration takes
    ``n_particles / fits_per_update`` ticks."""
    c1: float = Field(1.5, gt=0.0)
    """Cognitive acceleration (towards a particle's own best), Eq. 24."""
    c2: float = Field(1.5, gt=0.0)
    """Social acceleration (towards the swarm's best), Eq. 24."""
    w_max: float = Field(0.9, gt=0.0)
    """Inertia weight at the first iteration (Eq. 29)."""
    w_min: float = Field(0.4, gt=0.0)
    """Inertia weight the schedule decays to (Eq. 29)."""
    inertia_shape: float = Field(0.5, gt=0.0)
    """n in Eq. 29: w = (w_max - w_min) exp(-(iter / (n iter_max))^2) + w_min."""
    velocity_max_frac: float = Field(0.25, gt=0.0, le=1.0)
    """Velocity clamp as a fraction of each (log-)bound width."""
    init_spread_log: float = Field(0.7, gt=0.0)
    """Std of ln(tau) around the previous optimum for warm-started particles."""
    tau_ratio_min: float = Field(2.0, ge=1.0)
    """tau2 >= this x tau1: two branches that are really two."""
    seed: int = 0
    """Seed of the swarms' random numbers (combined with each cell's index): runs repeat exactly."""

    # --- divergence guard (estimate/guard.py) ------------------------------------------
    divergence_sigmas: float = Field(5.0, gt=1.0)
    """The model error is far beyond its running scale when its recent RMS (time constant
    ``divergence_fast_s``) exceeds this many times the running RMS (``divergence_scale_s``).
    Measured with ``hy-affrls-lpso`` and the SOC observer on the 13 real records (A123 DYN50;
    CALCE INR18650-20R, four profiles at 0, 25 and 45 C): at 5, excesses of at most 6 min,
    except in the last half hour of a CALCE discharge to empty (below ~8 % SOC, where constant
    parameters and the fitted OCV stop tracking: up to 30 min); a 50 mV offset added
    mid-record is caught one hold later on 11 of 13 (not on two 0 C records whose model error
    is itself 14-22 mV RMS), 20 mV on 8. At 3, three records trip with a 30 min hold."""
    divergence_floor_V: float = Field(1.0e-3, gt=0.0)
    """Floor of the running model-error scale, V: a model that tracks to 0.2 mV on a quiet
    bench must not call 5 mV a divergence (ADC resolution and OCV-table error are ~1 mV)."""
    divergence_fast_s: float = Field(60.0, gt=0.0)
    """Time constant of the recent model-error RMS, s: long enough that the error of one
    current pulse, or an error that changes sign, does not decide; short against the hold."""
    divergence_scale_s: float = Field(3600.0, gt=0.0)
    """Time constant of the running model-error RMS (the scale), s: several drive cycles. For
    this much data after a (re)start it learns every excited tick; later only errors within
    ``divergence_sigmas`` of it, so it follows a drifting level, not a jump (estimate/guard.py)."""
    divergence_hold_s: float = Field(3600.0, gt=0.0)
    """A model error in excess for this long (s of data) is a divergence: several slow time
    constants (tau2 ~ 100-1000 s), so a transient the model absorbs never trips it, and twice
    the 30 min the low-SOC tail of a discharge to empty kept the error in excess on the real
    records (``divergence_sigmas``): 1800 s tripped on the CALCE FUDS record at 45 C."""
    publish_average_tau1: float = Field(1.0, ge=0.0, le=100.0)
    """What is published (``params.csv``, CAN, MQTT) is R1, R2, tau1, tau2 averaged over this
    many of the cell's identified tau1 (first order; C = tau / R of the averages); the
    estimators and the model voltage use the raw values (``estimate/publish_average.py``). 0:
    publish the raw estimates. Measured on the known-truth DST (``bench/accuracy_synthetic.py``):
    largest R0+R1+R2 error 7.5 -> 1.8 %, ramp 7.0 -> 1.6 %, medians unchanged (the raw RLS takes
    a noisy sample's innovation whole into R1 and R2 right after each swarm's restart)."""
    divergence_soc_margin: float = Field(0.01, ge=0.0, le=0.5)
    """SOC (fraction) may leave [0, 1] by this much before it is a divergence: a coulomb count
    a per cent past full at the end of a charge is the capacity's error, not a lost state.
    Published SOC is clipped to [0, 1] (the count inside keeps its value)."""

    @property
    def fits_hysteresis_scale(self) -> bool:
        """``identify_hysteresis_scale`` resolved: explicit, or on when M is not learnt."""
        if self.identify_hysteresis_scale is not None:
            return self.identify_hysteresis_scale
        return not (self.observer.enabled and self.observer.learn_hysteresis)

    @model_validator(mode="after")
    def _check(self) -> Self:
        if self.lambda_min > self.lambda_max:
            raise ValueError("lambda_min must be <= lambda_max")
        if self.w_min > self.w_max:
            raise ValueError("w_min must be <= w_max")
        if self.min_window_s > self.window_s:
            raise ValueError("min_window_s must be <= window_s")
        if self.divergence_fast_s >= self.divergence_scale_s:
            raise ValueError("divergence_fast_s must be < divergence_scale_s")
        return self

"""Tuning of the SOC observer (``observer.py``) and the capacity estimate (``capacity.py``).

Every constant is physical and stated in the unit a battery engineer reasons in (V of model
error, C-rate of current offset, SOC per hour); none was fitted to one record.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class ObserverTuning(BaseModel):
    """The extended Kalman filter over [SOC of each cell, pack current offset]."""

    # strict: part of the daemon TOML, where a quoted number is refused, not coerced
    model_config = ConfigDict(
        extra="forbid", frozen=True, strict=True, use_attribute_docstrings=True
    )

    enabled: bool = True
    """Correct SOC, the current offset and capacity from the voltage. Off: SOC is a plain
    coulomb count from its start (the paper's Eq. 2), as before the observer existed."""
    update_period_s: float = Field(20.0, gt=0.0)
    """A measurement update every this many seconds of data. SOC moves by parts per thousand
    per minute; the model error of a real cell is correlated over tens of seconds (its fast
    branch), so faster updates count the same error many times. Measured on CALCE 45 C
    (``bench/accuracy_real.py``): at 10 s the observer chased the rest-point OCV table on DST
    (10.2 mV vs 2.4 without it); 20 s gives 2.1 (DST) and 2.7 mV (US06); at 60 s one US06
    swarm landed on a bad optimum (59.7 mV): the fusion is sensitive to it, see issue notes."""
    v_sigma_V: float = Field(5e-3, gt=0.0)
    """Std of the model error the observer assumes, V: an equivalent circuit on a real cell
    tracks within 2-10 mV; this keeps SOC from chasing the dynamics' residual."""
    r_dc_rel_sigma: float = Field(0.3, ge=0.0)
    """Relative std of the identified DC resistance R0 + R1 + R2 as the observer sees it: the
    model error under load grows as |I| x this x R_dc (resistance varies this much with SOC and
    temperature within a drive). Under a steady mean current a SOC error and an R2 error look
    alike; this makes SOC learn from light load and rests, where they do not. Measured lower:
    0.1 corrects a start SOC read from a voltage still relaxing (CALCE US06 25 C without
    ``--soc0``: 4.61 -> 3.21 mV, 7.91 -> 3.83 at 50 %; A123 DYN50 3.29 -> 3.05 mV) but lets the
    observer chase model error elsewhere (3-day ``bench/multiday.py``: day-1 SOC max 1.96 ->
    3.19 points with a start 30 points wrong, ``m-tilt`` R0+R1+R2 9.8 -> 14.7 %); 0.2 still
    ``m-tilt`` 14.8 % and the physics-based DST 15 C 5.97 -> 6.11 mV."""
    unconverged_wait_s: float = Field(3600.0, gt=0.0)
    """Until its parameters have converged once, a cell's SOC is corrected only at anchors and
    restarts (its model error is the start values', which a wrong start would turn into a
    current offset). After this much data (s) since the pack's last cell (re)started, still
    without convergence (too little excitation ever: a low-rate test, a constant-current
    discharge), it is corrected like a converged one, through its start values: without that
    the A123 C/27 test given to ``identify`` had one update and a SOC std of 27 points at its
    end, and a constant-current discharge from a start 10 points wrong stayed 10 points wrong.
    An hour: a drive-cycle record can take over half of one to converge (A123 DYN50: 2,159 s;
    with 1,800 s here its RMSE over SOC 95-15 % went 3.29 -> 3.36 mV)."""
    v_sigma_floor_V: float = Field(1e-3, gt=0.0)
    """Lower bound of the assumed model error at an anchor, V (a rested cell's voltage noise)."""
    gate_sigmas: float = Field(5.0, gt=1.0)
    """A cell whose innovation exceeds this many predicted std is left out of the update (a
    transient the model does not know, a glitch): counted as ``observer_gated``."""
    agree_sigmas: float = Field(3.0, gt=0.0)
    """In a pack of 3 or more cells, a cell whose innovation lies further than this many
    robust std of the cells' innovations (at least ``v_sigma_floor_V``) from their median
    teaches only its own SOC, not the pack's current offset or hysteresis map, nor the other
    cells' SOC through them (``observer_kernel.lone_cells``): an offset moves every cell's
    voltage alike, one cell off alone is that cell's own error. With +50 mV on every tenth
    sample of one cell's voltage (an intermittent sense wire; 8 cells of 100 Ah, 4 h) the
    offset read +3.51 A (truth 0) and the seven good cells' model error 1.9-7.5 mV instead of
    1.1-1.5; with this, -0.03 A and 1.12-1.70 mV."""
    soc_walk_per_sqrt_h: float = Field(0.003, ge=0.0)
    """SOC random walk, fraction per sqrt(hour): what the model cannot know (self-discharge,
    OCV drift with temperature)."""
    current_gain_sigma: float = Field(0.01, ge=0.0)
    """Relative error of the current sensor's gain: SOC uncertainty grows by this per unit of
    SOC moved (a 1 % gain error is 1 point per full cycle)."""
    offset_prior_C: float = Field(0.01, gt=0.0)
    """Prior std of the pack current-sensor offset, C-rate (1 % of 1C: a plain Hall sensor)."""
    offset_walk_C_per_sqrt_day: float = Field(0.001, ge=0.0)
    """Random walk of the offset, C-rate per sqrt(day) (sensor drift with temperature)."""
    offset_max_C: float = Field(0.05, gt=0.0)
    """The offset estimate is bounded to this, C-rate (a larger one is a broken sensor)."""
    start_soc_sigma_max: float = Field(0.3, gt=0.0, le=1.0)
    """Upper bound of the start SOC's std (a voltage that says nothing: a flat LFP plateau)."""
    given_soc_sigma: float = Field(0.01, gt=0.0)
    """Std of a start SOC the caller gives (``--soc0``, a checkpoint): a cycler's counter."""
    learn_ocv_sigma_V: float = Field(0.02, gt=0.0)
    """Parameters learn only while the OCV uncertainty |dOCV/dz| x std(SOC) is below this, V:
    a SOC error the observer has not removed yet would otherwise be learnt as resistance."""
    anchor_rest_taus: float = Field(3.0, gt=0.0)
    """A rest anchors SOC to the OCV once it has lasted this many identified slow time
    constants (the branches have relaxed to within exp(-3) = 5 %; ``rest_anchor.py``). In a
    pack of 3 or more cells a cell's slow time constant counts here at most as the cells'
    median: a capacity 3 % short inflates its cell's tau2 (the count's drift read as a slow
    relaxation) to 1,000-1,700 s, whose 3 tau2 outlast 50-60 min rests, so the anchor that
    would measure the capacity never came (8 cells of 70 Ah, two rests: 5 of 8 capacities
    measured, none of the cells 1.5-3 % short)."""
    anchor_min_rest_s: float = Field(600.0, ge=0.0)
    """... and at least this long, s."""
    restart_gap_s: float = Field(600.0, gt=0.0)
    """A gap in the data (a restart after downtime) longer than this re-anchors SOC from the
    first voltage after it, s; so does any gap (longer than the engine's ``gap_s``) that
    resumes under load: data lost mid-drive, whose charge the count never saw (10 min of an
    8-cell pack's drive without a current: model error 4.4 mV and an offset of -0.98 A with
    the count taken across it as a rest, 1.96 mV and -0.17 A re-anchored)."""
    learn_hysteresis: bool = True
    """Learn the hysteresis half-gap M per SOC region as states of the filter (one correction
    per knot for the pack: its cells are one type at one temperature), the configured M(z)
    table the prior (``hysteresis_map.py``). Rests resolve it: the branches relax, the
    hysteresis does not, and the count ties each rest's SOC to the others'."""
    hysteresis_error: bool = True
    """Estimate the error of the hysteresis state h (Eq. 5-6), one for the pack, as a state of
    the filter (``hysteresis_error.py``): its variance (1 - h^2) / 3 once the current has moved
    h, 0 where h saturates. The rate gamma is not measured, and under a drive's mixed current
    h settles where its charge balances; taken as exact, its error went into SOC at the rests.
    False: h as exact, as before."""
    rest_draw: bool = True
    """At rest h moves with what the pack draws as far as the filter knows it: the rests'
    reading less the offset estimate, shrunk by 2 std of the offset (``rest_anchor.rest_draw``;
    0 for a pack resting at 0 A). Measured on the 3-day ``rest-draw`` record (0.2 A drawn at
    every rest): day 3 tau1 19.9 -> 11.1 %, offset error -0.053 -> -0.025 A; every other
    scenario and the measured records the same. False: h holds at rest, as before."""
    play_error_variance: float = Field(1.0 / 3.0, ge=0.0, le=1.0)
    """Where h moves as a play (the cell config's ``hysteresis.law``, LFP by default), the
    variance its error returns to once the current has moved h, at least: the play sits at a
    branch, where (1 - h^2) / 3 is 0, and how soon it got there depends on gamma, which is not
    measured. Not used with Plett's law (its h under a drive sits between the branches)."""
    hysteresis_prior_rel: float = Field(0.25, gt=0.0)
    """Prior std of M at each knot, as a fraction of the table's M: the uncertainty the anchors
    assumed of the table before M was learnt (a C/20 test's half-gap against polarisation)."""
    hysteresis_prior_floor_V: float = Field(1e-3, ge=0.0)
    """Added to that prior std, V: a table of zeros may still be wrong by a rested cell's
    voltage noise (``v_sigma_floor_V``)."""
    hysteresis_walk_rel_per_sqrt_day: float = Field(0.1, ge=0.0)
    """Random walk of each knot, as a fraction of its prior std per sqrt(day): the prior
    uncertainty again after 100 days without a rest in that region (ageing, seasons)."""
    capacity_prior_rel: float = Field(0.05, gt=0.0)
    """Relative std of the configured capacity (the capacity estimate's prior)."""
    capacity_min_dsoc: float = Field(0.2, gt=0.0, lt=1.0)
    """Two anchors this far apart in SOC (fraction) measure the capacity."""
    capacity_fade_rel_per_sqrt_day: float = Field(0.005, ge=0.0)
    """Random walk of the capacity estimate, relative per sqrt(day): ageing and temperature."""

"""What an estimator bank reports at each identification tick (one value per cell)."""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


class Quality(IntEnum):
    """Quality flag of an estimate (also the CAN/MQTT code)."""

    CONVERGING = 0  #: not enough excitation seen yet; parameters are still the start values
    CONVERGED = 1  #: estimates settled and the model tracks the cell
    POORLY_EXCITED = 2  #: current carries too little information (rest, constant current)
    OUT_OF_BOUNDS = 3  #: the unconstrained estimate left the configured bounds and was clamped


VARIANTS = ("non-hy-affrls", "hy-affrls", "hy-affrls-lpso")


@dataclass(frozen=True, slots=True)
class Estimates:
    """Identified parameters and model outputs of ``n`` cells at time ``t_s``.

    All arrays have shape (n_cells,). Branch 1 is the fast RC branch (``tau1_s < tau2_s``).
    ``v_model_V`` is the a-priori model voltage (states propagated from the current only, with the
    parameters identified up to the previous tick; Eq. 9); ``v_meas_V`` the measured voltage.
    """

    t_s: float
    current_A: float
    R0_ohm: FloatArray
    R1_ohm: FloatArray
    C1_F: FloatArray
    R2_ohm: FloatArray
    C2_F: FloatArray
    tau1_s: FloatArray
    tau2_s: FloatArray
    M_V: FloatArray  #: hysteresis half-gap at the present SOC, V
    ocv_offset_V: FloatArray  #: identified OCV offset, V (0 where not identified)
    lambda_: FloatArray  #: forgetting factor per second of data, in [lambda_min, 1]
    h: FloatArray  #: hysteresis state in [-1, 1] (-1 after discharge)
    soc: FloatArray  #: coulomb-counted SOC, fraction
    v_model_V: FloatArray
    v_meas_V: FloatArray
    arx_error_V: FloatArray  #: one-step ARX/regression prediction error, V
    quality: IntArray

    @property
    def n_cells(self) -> int:
        return int(self.R0_ohm.shape[0])

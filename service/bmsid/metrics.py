"""Accuracy metrics of Eq. 31: max absolute error, RMSE (V) and MAPE (percent, not a fraction)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class VoltageMetrics:
    """Errors of a model voltage against the measurement over the finite samples."""

    n_samples: int
    max_abs_error_V: float
    rmse_V: float
    mape_pct: float

    def as_dict(self) -> dict[str, float | int | None]:
        """The fields for metrics.json; with no sample the errors are null, not a 0 that reads
        as a perfect fit (a ``no_data`` cell, a record without a model voltage)."""
        d: dict[str, float | int | None] = dict(asdict(self))
        if self.n_samples == 0:
            d.update(max_abs_error_V=None, rmse_V=None, mape_pct=None)
        return d


def voltage_metrics(v_meas_V: FloatArray, v_model_V: FloatArray) -> VoltageMetrics:
    """Eq. 31 on the samples where both voltages are finite (0 samples -> zeros, never NaN)."""
    m = np.asarray(v_meas_V, dtype=np.float64)
    p = np.asarray(v_model_V, dtype=np.float64)
    ok = np.isfinite(m) & np.isfinite(p) & (np.abs(m) > 0)
    if not ok.any():
        return VoltageMetrics(0, 0.0, 0.0, 0.0)
    err = m[ok] - p[ok]
    return VoltageMetrics(
        n_samples=int(ok.sum()),
        max_abs_error_V=float(np.max(np.abs(err))),
        rmse_V=float(np.sqrt(np.mean(err**2))),
        mape_pct=float(100.0 * np.mean(np.abs(err / m[ok]))),
    )

"""PNG figures in the style of the paper: parameters over time (Fig. 10), measured vs model
voltage with its error (Fig. 11), normalised parameters across profiles (Fig. 14).

matplotlib with the Agg backend (no display needed); every function writes one file.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
import numpy.typing as npt

matplotlib.use("Agg")

FloatArray = npt.NDArray[np.float64]
#: ``series(name, cell)``: times (s) and values of a plotted series of one cell (every tick, or
#: a min-max decimation: ``bmsid.offline.accumulate.MinMaxDecimator``). Names: the trace
#: fields, and ``error_V`` (measured - model, V).
Series = Callable[[str, int], tuple[FloatArray, FloatArray]]

#: (trace field, axis label, factor from SI to the plotted unit) for Fig. 10.
_PARAMS = (
    ("R0_ohm", "R0 / mOhm", 1e3),
    ("R1_ohm", "R1 / mOhm", 1e3),
    ("C1_F", "C1 / kF", 1e-3),
    ("R2_ohm", "R2 / mOhm", 1e3),
    ("C2_F", "C2 / kF", 1e-3),
    ("lambda_", "lambda", 1.0),
)


def plot_parameters(
    series: Series, cells: Sequence[int], names: Sequence[str], path: Path, title: str
) -> None:
    """Fig. 10: R0, R1, C1, R2, C2 and the forgetting factor over time (h), one line per cell."""
    fig, axes = plt.subplots(3, 2, figsize=(11, 8), sharex=True)
    for ax, (key, label, k) in zip(axes.ravel(), _PARAMS, strict=True):
        for c in cells:
            t, y = series(key, c)
            ax.plot(t / 3600.0, y * k, lw=0.8, label=names[c])
        ax.set_ylabel(label)
        if key.startswith("C"):
            ax.set_yscale("log")  # C = tau / R spikes while R passes near zero
        ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("time / h")
    if len(cells) > 1:
        axes[0, 0].legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_voltage(series: Series, cell: int, name: str, path: Path, title: str) -> None:
    """Fig. 11: measured and model voltage (V) over time, and the error (mV) below."""
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(11, 7), sharex=True,
                                   gridspec_kw={"height_ratios": [2, 1]})  # fmt: skip
    t_meas, meas = series("v_meas_V", cell)
    t_model, model = series("v_model_V", cell)
    t_err, err = series("error_V", cell)
    ax1.plot(t_meas / 3600.0, meas, lw=0.8, label="measured")
    ax1.plot(t_model / 3600.0, model, lw=0.8, ls="--", label="model (a priori)")
    ax1.set_ylabel("voltage / V")
    ax1.legend()
    ax1.grid(alpha=0.3)
    ax2.plot(t_err / 3600.0, err * 1e3, lw=0.6, color="tab:red")
    ax2.set_ylabel("error / mV")
    ax2.set_xlabel("time / h")
    ax2.grid(alpha=0.3)
    fig.suptitle(f"{title} - {name}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_consistency(
    normalised: Mapping[str, Mapping[str, Mapping[str, float]]],
    errors_pct: Mapping[str, Mapping[str, float]],
    path: Path,
    title: str,
) -> None:
    """Fig. 14: per variant, each parameter's profile median divided by its mean over the
    profiles (1 = consistent), one bar group per parameter, one bar per profile.

    ``normalised[variant][profile][parameter]``; ``errors_pct[variant][profile]`` goes in the
    legend.
    """
    variants = list(normalised)
    fig, axes = plt.subplots(1, len(variants), figsize=(4.5 * len(variants), 4), squeeze=False,
                             sharey=True)  # fmt: skip
    for ax, variant in zip(axes[0], variants, strict=True):
        profiles = list(normalised[variant])
        params = list(next(iter(normalised[variant].values()), {}))
        x = np.arange(len(params))
        width = 0.8 / max(len(profiles), 1)
        for j, prof in enumerate(profiles):
            vals = [normalised[variant][prof][p] for p in params]
            err = errors_pct[variant].get(prof, float("nan"))
            ax.bar(x + (j - (len(profiles) - 1) / 2) * width, vals, width,
                   label=f"{prof} ({err:.1f} %)")  # fmt: skip
        ax.axhline(1.0, color="k", lw=0.6)
        ax.set_xticks(x, [p.split("_")[0] for p in params])
        ax.set_title(variant)
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3, axis="y")
    axes[0, 0].set_ylabel("median / mean over profiles")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_rmse_bars(table: Sequence[Mapping[str, object]], path: Path) -> None:
    """Table 2 at a glance: RMSE (mV) per dataset (x) and variant (bars)."""
    datasets: list[str] = []
    variants: list[str] = []
    for row in table:
        if str(row["dataset"]) not in datasets:
            datasets.append(str(row["dataset"]))
        if str(row["algorithm"]) not in variants:
            variants.append(str(row["algorithm"]))
    rmse = {(str(r["dataset"]), str(r["algorithm"])): float(str(r["rmse_mV"])) for r in table}
    fig, ax = plt.subplots(figsize=(max(6.0, 1.6 * len(datasets)), 4))
    x = np.arange(len(datasets))
    width = 0.8 / max(len(variants), 1)
    for j, v in enumerate(variants):
        vals = [rmse.get((d, v), np.nan) for d in datasets]
        ax.bar(x + (j - (len(variants) - 1) / 2) * width, vals, width, label=v)
    ax.set_xticks(x, datasets, rotation=20, ha="right", fontsize=8)
    ax.set_ylabel("model-voltage RMSE / mV")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

"""The paper's comparison tables: Table 2 (accuracy and run time per profile, temperature and
variant, with the whole record and its start-up beside the evaluation window), the RMSE per SOC
band, and the parameter-consistency analysis of Fig. 14. Pure: rows in, text out.

Consistency (the paper gives no formula, Sec. 3.4): for each variant and each group of datasets
of one cell at one temperature, take the median of every identified parameter (R0, R1, C1, R2,
C2) over the evaluation window of each dataset; normalise each by its mean over the group's
datasets (1 = the same value on every profile). A dataset's consistency error is the mean over
the five parameters of |normalised - 1|, in percent; its spread is the same with the per-tick
values in place of the median (median over time of |p(t) / group mean - 1|), which also counts
how much the estimate wanders within the run. With two datasets the error is the same for both
(each sits as far from the mean as the other); the spread differs.

Held values: while a parameter sits on its bound (or after a divergence) the estimator publishes
its last good values (``Quality.OUT_OF_BOUNDS``). When one held value covers more than half of
the scored ticks, the median over time is that value, so the spread equals the error exactly: a
property of the median, not of the data (the AFFRLS baselines on CALCE 25 C DST hold one value
on 94 % of the ticks, tau1 on its bound). Each row therefore says on what share of the scored
ticks the values were held, and which parameter sat on a bound most (``HeldShare``).
"""

from __future__ import annotations

import csv
import io
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

#: Parameters the consistency analysis covers (the model's "full parameters").
CONSISTENCY_PARAMS = ("R0_ohm", "R1_ohm", "C1_F", "R2_ohm", "C2_F")

#: The paper's Table 2 RMSE in mV (70 Ah NMC cell), by (profile, temperature C) and variant.
PAPER_RMSE_mV: dict[tuple[str, float], dict[str, float]] = {
    ("DST", 15.0): {"non-hy-affrls": 30.0, "hy-affrls": 31.0, "hy-affrls-lpso": 11.8},
    ("DST", 25.0): {"non-hy-affrls": 43.0, "hy-affrls": 47.3, "hy-affrls-lpso": 21.4},
    ("DST", 35.0): {"non-hy-affrls": 37.8, "hy-affrls": 37.5, "hy-affrls-lpso": 14.2},
    ("BBDST", 15.0): {"non-hy-affrls": 31.0, "hy-affrls": 18.3, "hy-affrls-lpso": 14.6},
    ("BBDST", 25.0): {"non-hy-affrls": 44.0, "hy-affrls": 33.4, "hy-affrls-lpso": 28.4},
    ("BBDST", 35.0): {"non-hy-affrls": 30.4, "hy-affrls": 29.6, "hy-affrls-lpso": 17.3},
}
#: The paper's run times per run, s (their MATLAB on their PC): DST and BBDST ranges.
PAPER_RUNTIME_S = {"DST": (18.7, 22.3), "BBDST": (26.3, 35.4)}

_PROFILES = ("bbdst", "bjdst", "dst", "fuds", "us06", "udds", "hwfet", "ocv")
_PROFILE_RE = re.compile(r"(?:^|[_\-.])(" + "|".join(_PROFILES) + r"|dyn\d*)(?=$|[_\-.])", re.I)
_TEMP_RE = re.compile(r"(?:^|[_\-.])(-?\d+(?:\.\d+)?)C(?=$|[_\-.])")


@dataclass(frozen=True)
class DatasetLabel:
    """How a dataset is named in the tables: file stem, profile (e.g. DST) and temperature."""

    stem: str
    profile: str
    temperature_C: float | None

    @property
    def display(self) -> str:
        t = "" if self.temperature_C is None else f" {self.temperature_C:g}C"
        return f"{self.profile}{t}"


def file_stem(path: str | Path) -> str:
    name = Path(path).name
    for suffix in (".gz", ".csv", ".log"):
        if name.lower().endswith(suffix):
            name = name[: -len(suffix)]
    return name


def label_dataset(path: str | Path, temperature_C: float | None = None) -> DatasetLabel:
    """Profile and temperature from the file name (``..._dst_25C...``), the temperature falling
    back to ``temperature_C`` (e.g. the file's median temperature column)."""
    stem = file_stem(path)
    pm = _PROFILE_RE.search(stem)
    tm = _TEMP_RE.search(stem)
    profile = pm.group(1).upper() if pm else stem
    temp = float(tm.group(1)) if tm else temperature_C
    if temp is not None and not math.isfinite(temp):
        temp = None
    return DatasetLabel(stem=stem, profile=profile, temperature_C=temp)


def unique_displays(labels: Sequence[DatasetLabel]) -> list[str]:
    """Display names, falling back to the file stem where two datasets would look alike."""
    shown = [lb.display for lb in labels]
    return [lb.stem if shown.count(s) > 1 else s for lb, s in zip(labels, shown, strict=True)]


@dataclass(frozen=True)
class Table2Row:
    """One dataset x variant line of Table 2: errors over the evaluation window (``n_samples``
    ticks, V and %), run time (s), and the RMSE (V) of the whole record, of its first 10 % of
    the ticks (the start-up) and of the rest."""

    dataset: str
    profile: str
    temperature_C: float | None
    algorithm: str
    n_samples: int
    max_abs_error_V: float
    rmse_V: float
    mape_pct: float
    runtime_s: float
    rmse_whole_V: float = math.nan
    rmse_startup_V: float = math.nan
    rmse_after_startup_V: float = math.nan

    @property
    def rmse_mV(self) -> float:
        return 1e3 * self.rmse_V


def table2_csv(rows: Sequence[Table2Row]) -> str:
    buf = io.StringIO()
    names = list(Table2Row.__dataclass_fields__)
    w = csv.DictWriter(buf, fieldnames=names, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if v is None else v) for k, v in asdict(r).items()})
    return buf.getvalue()


def _fmt_t(t: float | None) -> str:
    return "-" if t is None else f"{t:g}"


def _mv(v: float, digits: int = 2) -> str:
    return "-" if not math.isfinite(v) else f"{1e3 * v:.{digits}f}"


def table2_markdown(rows: Sequence[Table2Row], window_text: str) -> str:
    """Table 2 as Markdown: the long table (the whole record, its first 10 % and the rest beside
    the evaluation window), an RMSE pivot over the window, and the paper's RMSE where a dataset
    has the paper's profile and temperature."""
    lines = [
        "## Table 2: model-voltage accuracy and run time",
        "",
        "RMSE over the whole record (every tick), over its first 10 % of the ticks (start-up, "
        "converging from the start values) and over the rest; max error, RMSE and MAPE over the "
        f"evaluation window ({window_text}); run time = wall time of the identification loop.",
        "",
        "| dataset | profile | T / C | algorithm | RMSE whole / mV | RMSE first 10 % / mV "
        "| RMSE after 10 % / mV | max error in window / mV | RMSE in window / mV "
        "| MAPE in window / % | run time / s |",
        "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r.dataset} | {r.profile} | {_fmt_t(r.temperature_C)} | {r.algorithm} "
            f"| {_mv(r.rmse_whole_V)} | {_mv(r.rmse_startup_V)} | {_mv(r.rmse_after_startup_V)} "
            f"| {_mv(r.max_abs_error_V, 1)} | {_mv(r.rmse_V)} | {r.mape_pct:.3f} "
            f"| {r.runtime_s:.1f} |"
        )
    datasets = list(dict.fromkeys(r.dataset for r in rows))
    variants = list(dict.fromkeys(r.algorithm for r in rows))
    by = {(r.dataset, r.algorithm): r for r in rows}
    lines += ["", "RMSE / mV in the evaluation window (ours):", ""]
    lines += ["| algorithm | " + " | ".join(datasets) + " |"]
    lines.append("|---|" + "---:|" * len(datasets))
    for v in variants:
        cells = [f"{by[(d, v)].rmse_mV:.2f}" if (d, v) in by else "-" for d in datasets]
        lines.append(f"| {v} | " + " | ".join(cells) + " |")
    first = {d: next(r for r in rows if r.dataset == d) for d in datasets}
    keys: dict[str, tuple[str, float]] = {}
    for d in datasets:
        temp = first[d].temperature_C
        if temp is not None and (first[d].profile, temp) in PAPER_RMSE_mV:
            keys[d] = (first[d].profile, temp)
    if keys:
        lines += ["", "RMSE / mV in the paper (Table 2, their 70 Ah cell, same profile and "
                  "temperature):", ""]  # fmt: skip
        lines.append("| algorithm | " + " | ".join(keys) + " |")
        lines.append("|---|" + "---:|" * len(keys))
        for v in variants:
            cells = [f"{PAPER_RMSE_mV[k].get(v, math.nan):.1f}" for k in keys.values()]
            lines.append(f"| {v} (paper) | " + " | ".join(cells) + " |")
        lines.append("")
        lines.append(
            "Paper run times per run: DST 18.7-22.3 s, BBDST 26.3-35.4 s (MATLAB, their PC)."
        )
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class SocBandRow:
    """Eq. 31 of one dataset x variant over the ticks of one SOC band (pooled over the cells):
    ``band`` as labelled in metrics.json (``"10-20 %"``), its bounds as fractions (None: open),
    ``n_samples`` ticks, errors in V and %."""

    dataset: str
    profile: str
    temperature_C: float | None
    algorithm: str
    band: str
    soc_lo: float | None
    soc_hi: float | None
    n_samples: int
    max_abs_error_V: float
    rmse_V: float
    mape_pct: float


def soc_band_rows(
    dataset: str,
    profile: str,
    temperature_C: float | None,
    algorithm: str,
    bands: Sequence[Mapping[str, Any]],
) -> list[SocBandRow]:
    """The rows of one run from the ``soc_bands`` list of its metrics.json."""
    return [
        SocBandRow(
            dataset=dataset,
            profile=profile,
            temperature_C=temperature_C,
            algorithm=algorithm,
            band=str(b["band"]),
            soc_lo=b["soc_lo"],
            soc_hi=b["soc_hi"],
            n_samples=int(b["n_samples"]),
            max_abs_error_V=float(b["max_abs_error_V"]),
            rmse_V=float(b["rmse_V"]),
            mape_pct=float(b["mape_pct"]),
        )
        for b in bands
    ]


def soc_bands_csv(rows: Sequence[SocBandRow]) -> str:
    """One line per dataset, variant and non-empty SOC band."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(SocBandRow.__dataclass_fields__), lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if v is None else v) for k, v in asdict(r).items()})
    return buf.getvalue()


def _band_order(rows: Sequence[SocBandRow]) -> list[str]:
    """Band labels present, in SOC order (below 0 first, above 100 last)."""

    def key(label: str) -> float:
        r = next(x for x in rows if x.band == label)
        return -math.inf if r.soc_lo is None else r.soc_lo

    return sorted(dict.fromkeys(r.band for r in rows), key=key)


def soc_bands_markdown(rows: Sequence[SocBandRow], soc_text: str) -> str:
    """RMSE per SOC band as Markdown, one line per dataset and variant, each cell
    ``RMSE mV (ticks)``; ``-`` where the run never reached the band."""
    lines = [
        "## Model-voltage RMSE per SOC band",
        "",
        f"RMSE / mV (ticks in the band) per 10 % SOC band over every tick of the record, the "
        f"start-up included. SOC: {soc_text}.",
        "",
    ]
    if not rows:
        lines.append("No tick was scored.")
        return "\n".join(lines) + "\n"
    bands = _band_order(rows)
    lines.append("| dataset | algorithm | " + " | ".join(bands) + " |")
    lines.append("|---|---|" + "---:|" * len(bands))
    by = {(r.dataset, r.algorithm, r.band): r for r in rows}
    runs = list(dict.fromkeys((r.dataset, r.algorithm) for r in rows))
    for d, a in runs:
        cells = [
            f"{1e3 * by[(d, a, b)].rmse_V:.2f} ({by[(d, a, b)].n_samples})"
            if (d, a, b) in by
            else "-"
            for b in bands
        ]
        lines.append(f"| {d} | {a} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


#: A held share from which a consistency row is flagged: its median is then one held value.
HELD_FLAG_SHARE = 0.5


@dataclass(frozen=True)
class HeldShare:
    """Over a run's scored ticks (first cell): the share whose published parameters were held
    (the last good values: quality out_of_bounds or diverged), and the parameter most often on
    a bound with its share (None: none on a bound)."""

    held: float
    bound_param: str | None = None
    bound: float = 0.0

    @classmethod
    def of_cell(cls, cell: Mapping[str, Any]) -> HeldShare:
        """From a cell's entry of metrics.json (``scoring.metrics_document``)."""
        return cls(cell["held_share"], cell["most_on_bound"], cell["most_on_bound_share"])

    @property
    def flagged(self) -> bool:
        return self.held >= HELD_FLAG_SHARE

    def text(self) -> str:
        """What was held, in words: the share and the parameter most on a bound."""
        bound = (
            f"; {self.bound_param} on a bound on {100 * self.bound:.0f} %"
            if self.bound_param
            else ""
        )
        return (
            f"parameters held (last good values) on {100 * self.held:.0f} % of the scored "
            f"ticks{bound}"
        )

    def bound_text(self) -> str:
        if self.bound_param is None:
            return "-"
        return f"{self.bound_param.split('_')[0]} {100 * self.bound:.0f} %"


@dataclass(frozen=True)
class Consistency:
    """Fig. 14 for one group (cell and temperature) and one variant.

    ``medians[dataset][parameter]`` in SI units (ohm, F); ``normalised[dataset][parameter]`` =
    the dataset's median / the group mean of the medians; ``error_pct[dataset]`` = mean over the
    parameters of |normalised - 1| x 100 (agreement of the levels); ``spread_pct[dataset]`` =
    mean over the parameters of the median over time of |p(t) / group mean - 1| x 100 (also
    counts how much each estimate wanders within the run; NaN without trajectories);
    ``held[dataset]`` where the values were held (none when not given).
    """

    group: str
    algorithm: str
    medians: dict[str, dict[str, float]]
    normalised: dict[str, dict[str, float]]
    error_pct: dict[str, float]
    spread_pct: dict[str, float]
    held: dict[str, HeldShare] = field(default_factory=dict)

    @property
    def mean_error_pct(self) -> float:
        vals = list(self.error_pct.values())
        return sum(vals) / len(vals) if vals else math.nan


def _median(values: Sequence[float]) -> float:
    v = sorted(x for x in values if math.isfinite(x))
    if not v:
        return math.nan
    k = len(v) // 2
    return v[k] if len(v) % 2 else 0.5 * (v[k - 1] + v[k])


def consistency(
    group: str,
    algorithm: str,
    medians: Mapping[str, Mapping[str, float]],
    trajectories: Mapping[str, Mapping[str, Sequence[float]]] | None = None,
    held: Mapping[str, HeldShare] | None = None,
) -> Consistency:
    """Consistency of several datasets' parameters (module docstring); ``trajectories``
    [dataset][parameter] are the scored per-tick values, for ``spread_pct``; ``held`` [dataset]
    where they were held, shown beside them."""
    datasets = list(medians)
    norm: dict[str, dict[str, float]] = {d: {} for d in datasets}
    ref: dict[str, float] = {}
    for p in CONSISTENCY_PARAMS:
        vals = [float(medians[d][p]) for d in datasets]
        finite = [v for v in vals if math.isfinite(v)]
        ref[p] = sum(finite) / len(finite) if finite else math.nan
        for d, v in zip(datasets, vals, strict=True):
            norm[d][p] = v / ref[p] if ref[p] and math.isfinite(ref[p]) else math.nan
    n_p = len(CONSISTENCY_PARAMS)
    err = {
        d: 100.0 * sum(abs(norm[d][p] - 1.0) for p in CONSISTENCY_PARAMS) / n_p for d in datasets
    }
    spread: dict[str, float] = {}
    for d in datasets:
        if trajectories is None or d not in trajectories:
            spread[d] = math.nan
            continue
        per_param = [
            _median([abs(x / ref[p] - 1.0) for x in trajectories[d][p]]) for p in CONSISTENCY_PARAMS
        ]
        spread[d] = 100.0 * sum(per_param) / n_p
    return Consistency(
        group=group,
        algorithm=algorithm,
        medians={d: {p: float(medians[d][p]) for p in CONSISTENCY_PARAMS} for d in datasets},
        normalised=norm,
        error_pct=err,
        spread_pct=spread,
        held=dict(held or {}),
    )


def consistency_csv(results: Sequence[Consistency]) -> str:
    buf = io.StringIO()
    head = ["group", "algorithm", "dataset"]
    head += [f"{p}_median" for p in CONSISTENCY_PARAMS]
    head += [f"{p}_normalised" for p in CONSISTENCY_PARAMS]
    head += ["consistency_error_pct", "trajectory_spread_pct", "held_pct", "most_on_bound",
             "most_on_bound_pct"]  # fmt: skip
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(head)
    for c in results:
        for d in c.medians:
            w.writerow(
                [c.group, c.algorithm, d]
                + [f"{c.medians[d][p]:.6g}" for p in CONSISTENCY_PARAMS]
                + [f"{c.normalised[d][p]:.4f}" for p in CONSISTENCY_PARAMS]
                + [f"{c.error_pct[d]:.2f}", f"{c.spread_pct[d]:.2f}"]
                + _held_csv(c.held.get(d))
            )
    return buf.getvalue()


def _held_csv(h: HeldShare | None) -> list[str]:
    if h is None:
        return ["", "", ""]
    return [f"{100 * h.held:.1f}", h.bound_param or "", f"{100 * h.bound:.1f}"]


def _held_md(h: HeldShare | None) -> str:
    if h is None:
        return "- | -"
    return f"{100 * h.held:.0f}{' **!**' if h.flagged else ''} | {h.bound_text()}"


def consistency_markdown(results: Sequence[Consistency]) -> str:
    lines = [
        "## Parameter consistency across profiles (Fig. 14)",
        "",
        "Normalised = a parameter's median over the evaluation window / its mean over the "
        "datasets of the group. Error = mean |normalised - 1| over R0, R1, C1, R2, C2 (do the "
        "profiles agree?); spread = mean over the parameters of the median over time of "
        "|p(t) / group mean - 1| (also counts how much the estimate wanders within the run). "
        "Held = share of the scored ticks whose published parameters were the last good "
        "values (quality out_of_bounds or diverged); on a bound = the parameter most often on "
        "its bound and its share of the scored ticks.",
        "",
    ]
    if not results:
        lines.append("No group has two or more datasets of one cell at one temperature.")
        return "\n".join(lines) + "\n"
    short = [p.split("_")[0] for p in CONSISTENCY_PARAMS]
    lines.append(
        "| group | algorithm | dataset | "
        + " | ".join(short)
        + " | error / % | spread / % | held / % | on a bound |"
    )
    lines.append("|---|---|---|" + "---:|" * (len(short) + 3) + "---|")
    for c in results:
        for d in c.medians:
            vals = " | ".join(f"{c.normalised[d][p]:.3f}" for p in CONSISTENCY_PARAMS)
            lines.append(
                f"| {c.group} | {c.algorithm} | {d} | {vals} | {c.error_pct[d]:.1f} "
                f"| {c.spread_pct[d]:.1f} | {_held_md(c.held.get(d))} |"
            )
    if any(h.flagged for c in results for h in c.held.values()):
        lines += [
            "",
            f"**!** held on {100 * HELD_FLAG_SHARE:.0f} % or more of the scored ticks: the "
            "medians are held last good values (the estimate stopped where a parameter hit "
            "its bound; one held value on over half of them makes spread = error by "
            "construction): the row does not measure a run-long estimate.",
        ]
    lines += [
        "",
        "Paper (15 C, DST / BBDST, its definition unstated): AFFRLS 26.4 % / 12.3 %, "
        "AFFRLS-LPSO 16.5 % / 9.9 %.",
    ]
    return "\n".join(lines) + "\n"

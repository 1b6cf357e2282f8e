"""What limits the cpu-online network: accuracy against Adam steps and distinct training
segments together, a saturating surface fitted to the runs, and the budget at which it meets
the classical baselines.

Reads the CSV that ``cloudpose experiments --group shared --group diagnostics --preset
cpu-online --against cpu-online --out reports/diagnostics/cpu_online_experiments.md`` writes
beside its Markdown. A run of shared-0 is kept when it changes nothing but :data:`KEPT`: its
steps (``train.epochs``, ``data.online_epoch_segments``), its distinct segments (steps x batch /
``data.online_reuse``), its synthesis version and workers, and its width::

    python reports/diagnostics/online_budget.py reports/diagnostics/cpu_online_experiments.csv \\
        --out reports/diagnostics/online_budget.png \\
        --baseline-run "FPFH + RANSAC=cpu-online:baseline-fpfh" \\
        --baseline-run "point-pair features=cpu-online:baseline-ppf"

Each ``--baseline-run NAME=PRESET:VARIANT`` reads a classical method's figures from the MLflow
store (rotation < 10 deg modulo symmetry and ADS AUC, without and with ICP: the mean over its
seeds of the runs on every test instance, as Table I has them); ``--baseline
NAME=ROT,ROT_ICP,ADS,ADS_ICP`` gives them as numbers (percent) instead.

The surface, for each of the four figures y (percent), over the width-1 runs:

    y(S, D) = A - B (D / 32768)^-a - C (S / 4096)^-c

S Adam steps, D distinct segments: A is where more of both leads, the D term what fresh data
buys at enough steps, the S term what steps buy on enough data. Fitted by least squares over
every seed's run; the intervals are the 2.5-97.5 percentiles of 2,000 fits to the runs
resampled with replacement (a fit that does not converge is dropped and counted). The budget
at which the network meets a baseline is read along reuse 1 (D = 32 S: every segment once,
the cheapest synthesis-free way to both) and along reuse 2; "beyond" when the fit's plateau
A lies below the baseline.
"""

from __future__ import annotations

import argparse
import re
import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from scipy.optimize import OptimizeWarning, curve_fit

from cloudpose.registry import resolve

_PRESET = resolve("shared-0", "cpu-online")
BATCH, REUSE = _PRESET.train.batch_size, _PRESET.data.online_reuse
KEPT = (
    "train.epochs",
    "data.online_reuse",
    "data.online_version",
    "model.width",
    # where chunks are made and how many steps an epoch counts (when validation runs): neither
    # changes a step's batch nor the schedule, which spans the run (the `gpu` preset sets both)
    "data.online_workers",
    "data.online_epoch_segments",
)
FIGURES = {
    "test": ("test < 10° mod sym (%)", "rotation < 10° mod sym (%)"),
    "test_icp": ("test + ICP < 10° mod sym (%)", "+ ICP: rotation < 10° mod sym (%)"),
    "ads": ("test ADS AUC", "ADS AUC"),
    "ads_icp": ("test + ICP ADS AUC", "+ ICP: ADS AUC"),
}
"""Figure -> (column of the experiment log, label)."""
D0, S0 = 32768, 4096
BOOT = 2000


def budget_table(log: pd.DataFrame) -> pd.DataFrame:
    """One row per kept run: its changes parsed, steps, distinct segments and figures."""
    rows = []
    for _, r in log.iterrows():
        if not str(r["run"]).startswith("shared-0/"):
            continue
        changes = (
            {}
            if r["changes"] == "(none)"
            else dict(kv.split("=", 1) for kv in re.split(r",\s*", r["changes"]))
        )
        if set(changes) - set(KEPT):
            continue
        reuse = int(changes.get("data.online_reuse", REUSE))
        row = {
            "run": r["run"],
            "reuse": reuse,
            "width": float(changes.get("model.width", 1.0)),
            "version": int(changes.get("data.online_version", _PRESET.data.online_version)),
            "steps": int(r["Adam steps"]),
            "segments": int(r["Adam steps"]) * BATCH // reuse,
            "real": r["real < 10° mod sym (%)"],
            "real_icp": r["real + ICP < 10° mod sym (%)"],
        }
        for key, (column, _) in FIGURES.items():
            row[key] = r[column] if column in r else np.nan
        rows.append(row)
    return pd.DataFrame(rows)


def surface(x: np.ndarray, A: float, B: float, a: float, C: float, c: float) -> np.ndarray:
    S, D = x
    return A - B * (D / D0) ** (-a) - C * (S / S0) ** (-c)


_P0 = (65.0, 15.0, 0.5, 3.0, 0.5)
_BOUNDS = ([0, 0, 0.05, 0, 0.05], [100, 200, 3, 200, 3])


def _fit(S: np.ndarray, D: np.ndarray, y: np.ndarray) -> np.ndarray | None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OptimizeWarning)
        try:
            p, _ = curve_fit(surface, (S, D), y, p0=_P0, bounds=_BOUNDS, maxfev=20000)
        except (RuntimeError, ValueError):
            return None
    return p


def meet_steps(p: np.ndarray, target: float, reuse: int) -> float:
    """Adam steps at which the fitted surface along ``D = BATCH S / reuse`` reaches
    ``target`` (inf when its plateau does not; 0 when it is there from the start)."""
    lo, hi = 2.0**8, 2.0**30
    f = lambda s: surface((s, BATCH * s / reuse), *p) - target  # noqa: E731
    if f(hi) < 0:
        return float("inf")
    if f(lo) >= 0:
        return lo
    for _ in range(100):
        mid = np.sqrt(lo * hi)
        lo, hi = (mid, hi) if f(mid) < 0 else (lo, mid)
    return float(hi)


def fit_figure(t: pd.DataFrame, key: str, seed: int = 0) -> dict:
    """Point fit and bootstrap of one figure over the width-1 runs that have it."""
    g = t[(t["width"] == 1.0) & t[key].notna()]
    S, D, y = (g[c].to_numpy(float) for c in ("steps", "segments", key))
    p = _fit(S, D, y)
    rng = np.random.default_rng(seed)
    boots, failed = [], 0
    for _ in range(BOOT):
        i = rng.integers(0, len(y), len(y))
        if len(np.unique(np.stack([S[i], D[i]]), axis=1).T) < 5:
            failed += 1
            continue
        q = _fit(S[i], D[i], y[i])
        if q is None:
            failed += 1
        else:
            boots.append(q)
    return {"params": p, "boots": np.array(boots), "failed": failed, "n": len(y)}


def _interval(values: np.ndarray) -> tuple[float, float]:
    return float(np.percentile(values, 2.5)), float(np.percentile(values, 97.5))


def _steps_text(point: float, lo: float, hi: float) -> str:
    def one(s: float) -> str:
        return "beyond" if not np.isfinite(s) else f"{s / 1000:.0f}k"

    return f"{one(point)} [{one(lo)}, {one(hi)}]"


def fit_table(t: pd.DataFrame, baselines: dict[str, list[float]]) -> pd.DataFrame:
    """Per figure: the fit's plateau A with its interval, the residual, and for each baseline
    the steps at which reuse 1 and reuse 2 meet it."""
    rows = []
    for i, (key, (_, label)) in enumerate(FIGURES.items()):
        f = fit_figure(t, key)
        p, boots = f["params"], f["boots"]
        if p is None:
            rows.append({"figure": label, "runs": f["n"], "plateau A": "no fit"})
            continue
        g = t[(t["width"] == 1.0) & t[key].notna()]
        resid = g[key].to_numpy(float) - surface((g["steps"], g["segments"]), *p)
        lo, hi = _interval(boots[:, 0])
        row = {
            "figure": label,
            "runs": f["n"],
            "plateau A": f"{p[0]:.1f} [{lo:.1f}, {hi:.1f}]",
            "data exponent a": f"{p[2]:.2f}",
            "steps exponent c": f"{p[4]:.2f}",
            "rms residual": f"{np.sqrt(np.mean(resid**2)):.1f}",
            "resamples": f"{len(boots)} of {BOOT}",
        }
        for name, values in baselines.items():
            target = values[i]
            row[f"{name}"] = f"{target:.1f}"
            for reuse in (1, 2):
                pts = np.array([meet_steps(q, target, reuse) for q in boots])
                lo_s, hi_s = np.percentile(pts, 2.5), np.percentile(pts, 97.5)
                row[f"steps to {name}, reuse {reuse}"] = _steps_text(
                    meet_steps(p, target, reuse), lo_s, hi_s
                )
        rows.append(row)
    return pd.DataFrame(rows)


def plot(t: pd.DataFrame, baselines: dict[str, list[float]], out: Path) -> None:
    fig, axes = plt.subplots(1, 4, figsize=(18, 4.2))
    w1 = t[t["width"] == 1.0]
    s_grid = np.geomspace(1024, 2**16, 60)
    for ax, (i, (key, (_, label))) in zip(axes, enumerate(FIGURES.items()), strict=True):
        f = fit_figure(t, key)
        have = w1[w1[key].notna()]
        for j, reuse in enumerate(sorted(set(have["reuse"]) | {1, 2})):
            color = f"C{j}"
            g = have[have["reuse"] == reuse]
            for version, marker in ((1, "o"), (2, "^"), (3, "s")):
                h = g[g["version"] == version]
                if len(h):
                    ax.plot(h["steps"], h[key], marker, color=color, alpha=0.8)
            if f["params"] is not None:
                ax.plot(
                    s_grid,
                    surface((s_grid, BATCH * s_grid / reuse), *f["params"]),
                    "-",
                    color=color,
                    label=f"reuse {reuse} ({BATCH // reuse} fresh segments a step)",
                )
        for k, (name, values) in enumerate(baselines.items()):
            ax.axhline(values[i], color="k", ls=("--", ":")[k % 2], lw=1, label=name)
        ax.set_xscale("log", base=2)
        ax.set_xlabel("Adam steps (batch 32)")
        ax.set_title(label, fontsize=10)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("percent, synthetic test set")
    axes[-1].legend(fontsize=7, loc="lower right")
    fig.suptitle(
        "cpu-online shared-0: runs (o synthesis v1, ^ v2, s v3) and the fitted surface "
        "y = A - B (D/32k)^-a - C (S/4k)^-c along each reuse"
    )
    fig.tight_layout()
    fig.savefig(out, dpi=110)


def _baselines(specs: list[str]) -> dict[str, list[float]]:
    out = {}
    for spec in specs:
        name, _, values = spec.partition("=")
        numbers = [float(v) for v in values.split(",")]
        if not name or len(numbers) != len(FIGURES):
            raise SystemExit(f"--baseline {spec!r}: expected NAME=ROT,ROT_ICP,ADS,ADS_ICP")
        out[name] = numbers
    return out


STORE_METRICS = (
    "test/rot_sym_lt_10deg",
    "test_icp/rot_sym_lt_10deg",
    "test/ads_auc",
    "test_icp/ads_auc",
)
"""The logged metrics (fractions) of :data:`FIGURES`, in its order."""


def _baselines_from_store(specs: list[str]) -> dict[str, list[float]]:
    """``NAME=PRESET:VARIANT`` -> the mean over seeds of the variant's runs in the MLflow store
    (the runs Table I is rendered from: ``cloudpose.report.runs.load_runs``), in percent."""
    from cloudpose.report.runs import load_runs
    from cloudpose.store.tracking import tracking_uri

    out: dict[str, list[float]] = {}
    loaded = {}  # preset -> its RunSet, read from the store once
    for spec in specs:
        name, _, where = spec.partition("=")
        preset, _, variant = where.partition(":")
        if not (name and preset and variant):
            raise SystemExit(f"--baseline-run {spec!r}: expected NAME=PRESET:VARIANT")
        if preset not in loaded:
            loaded[preset] = load_runs(preset)
        records = [r for r in loaded[preset].of(variant) if r.subsample == "all"]
        if not records:
            raise SystemExit(
                f"--baseline-run {spec!r}: no finished run of {variant} on every test instance "
                f"of {preset} in the MLflow store ({tracking_uri()})"
            )
        out[name] = [100 * float(np.nanmean([r.metric(k) for r in records])) for k in STORE_METRICS]
        seeds = ", ".join(str(r.seed) for r in records)
        print(
            f"{name}: {variant} of {preset}, seeds {seeds}: "
            + ", ".join(f"{v:.1f}" for v in out[name])
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", type=Path, help="CSV of the cpu-online experiment log")
    ap.add_argument(
        "--out", type=Path, required=True, help="PNG to write (the tables beside it as .csv)"
    )
    ap.add_argument("--baseline", action="append", default=[], help="NAME=ROT,ROT_ICP,ADS,ADS_ICP")
    ap.add_argument(
        "--baseline-run",
        action="append",
        default=[],
        help="NAME=PRESET:VARIANT: a baseline's figures read from the MLflow store",
    )
    a = ap.parse_args()
    baselines = {**_baselines(a.baseline), **_baselines_from_store(a.baseline_run)}
    t = budget_table(pd.read_csv(a.log))
    t.to_csv(a.out.with_suffix(".csv"), index=False, float_format="%.1f")
    fits = fit_table(t, baselines)
    fits.to_csv(a.out.with_name(a.out.stem + "_fit.csv"), index=False)
    plot(t, baselines, a.out)
    print(t.to_string(index=False))
    print()
    print(fits.T.to_string(header=False))


if __name__ == "__main__":
    main()

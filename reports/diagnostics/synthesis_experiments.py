"""Synthesis settings that make training segments more like real ones (masks that bleed,
``data.online_bleed``; depth errors correlated between pixels, ``data.online_smooth`` and
``data.online_noise_corr``): each
setting against the same runs without it, paired by seed, on the synthetic test set and the
real development frames.

The runs are the finished shared-0 runs of each ``--preset`` whose config differs from the
preset's own at most in :data:`AXES`, with synthesis version 3 (the version that has these
settings). For each setting and each seed that also has a run without any (``none``: the same
scenes and initial weights; the masks or the depth differ, and so do the random draws after
them in a scene, its noise and FPS starts, for both branches: a translation-only setting's
rotation branch is another draw, not the plain run's), the difference of
every figure, without and with ICP, with the two-level bootstrap interval of the paper's claims
(:func:`cloudpose.report.stats.bootstrap_difference`: seeds and instances redrawn together)::

    python reports/diagnostics/synthesis_experiments.py --preset cpu-online --preset cpu-online-4x \\
        --out reports/diagnostics/synthesis_experiments.md

Run it in the project folder that holds the runs (the MLflow store of ``MLFLOW_TRACKING_URI``
or ``./mlruns``). Writes the Markdown and a CSV beside it (one row per preset, setting, set,
stage and figure). Each ``--stress DIR`` is the results folder of a ``cloudpose stress`` sweep
of one of these runs (``--run`` its folder, run id or name; the run is found by the run id the
sweep keeps, else by its folder name); the
Markdown then lists the ``--perturbation`` (default ``dilate``) curve of each setting against
``none``,
``*_stress.csv`` holds its summaries and ``*_stress.png`` plots them. ``--stress-csv FILE``
reads such a CSV back (the curves of sweeps whose folders are gone, e.g. the committed
``reports/diagnostics/synthesis_experiments_stress.csv``): a sweep given by ``--stress`` replaces
its rows for the same run (preset, setting, seed), source, level and stage.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from cloudpose.config import VERSION_3_SETTINGS, Config
from cloudpose.files import atomic_text, atomic_write
from cloudpose.report.experiments import config_changes
from cloudpose.report.real import object_pose
from cloudpose.report.runs import TEST_KEY, RunRecord, _record
from cloudpose.report.stats import auc_of_rows, share_below
from cloudpose.store import tracking
from cloudpose.studies.stress import collect

AXES = frozenset(
    {
        "data.online_version",
        "data.online_bleed_branch",
        *(f"data.{name}" for name in VERSION_3_SETTINGS),
    }
)
"""The settings an experiment here may change from its preset."""
NONE = "none"
"""The setting of the runs every other is paired with."""

FIGURES = (  # metric, per-instance column (after the stage's prefix), stat of (R, N) rows
    ("ADS AUC", "ads", auc_of_rows),
    ("rot < 10 deg mod sym", "rot_sym_err_deg", share_below(10.0)),
    ("translation < 1 cm", "trans_err", share_below(0.01)),
)
SETS = (("test", "synthetic test set"), ("real", "real development frames"))
STAGES = (("net_", "network"), ("icp_", "+ ICP"))


def setting(data) -> str:
    """The synthesis setting of a run's ``data`` config in words (:data:`NONE` for neither)."""
    parts = []
    if data.online_bleed:
        branch = "" if data.online_bleed_branch == "both" else f" ({data.online_bleed_branch})"
        parts.append(f"bleed {data.online_bleed:g}{branch}")
    if data.online_smooth:
        parts.append(f"smooth {data.online_smooth:g} px")
    if data.online_noise_corr:
        parts.append(f"correlated noise {data.online_noise_corr:g} px")
    return ", ".join(parts) or NONE


def synthesis_runs(client, preset: str, folders: dict[str, tuple] | None = None):
    """setting -> seed -> the newest finished shared-0 run of ``preset`` with that setting;
    each chosen run's id and folder name (tag ``run_dir``) -> (preset, setting, seed) go into
    ``folders`` when given."""
    out: dict[str, dict[int, RunRecord]] = {}
    for run in tracking.find_runs(client, variant="shared-0", preset=preset):  # newest first
        tags = run.data.tags
        if not tags.get("seed") or TEST_KEY not in run.data.metrics:
            continue
        try:  # a run kept as metadata only (no artifacts) cannot say what it changed
            path = tracking.download_artifact(client, run, "config.json")
            cfg = Config.from_dict(json.loads(Path(path).read_text()))
        except (OSError, ValueError):
            continue
        changes = set(config_changes(cfg)) - {"preset"}
        if changes - AXES or cfg.data.train_source != "online" or cfg.data.online_version < 3:
            continue
        seed = int(tags["seed"])
        label = setting(cfg.data)
        by_seed = out.setdefault(label, {})
        if seed not in by_seed:
            by_seed[seed] = _record(run, ("shared-0", seed), preset, tags.get("data", ""), client)
            if folders is not None:
                folders[run.info.run_id] = (preset, label, seed)
                if tags.get("run_dir"):
                    folders[Path(tags["run_dir"]).name] = (preset, label, seed)
    return out


def _tables(runs: dict[int, RunRecord], name: str) -> dict[int, pd.DataFrame]:
    """seed -> the instance table of evaluation ``name``, sorted by (frame, instance)."""
    out = {}
    for seed, run in runs.items():
        df = run.instances(name)
        if df is None:
            raise FileNotFoundError(
                f"run {run.run_id} ({run.preset} seed {seed}): no per-instance table of "
                f"eval/{name} (evaluate it again: cloudpose evaluate --run ...)"
            )
        out[seed] = df.sort_values(["frame_id", "instance"], kind="stable")
    return out


def _column(tables: dict[int, pd.DataFrame], column: str) -> dict[int, np.ndarray]:
    """seed -> per-instance values of ``column``; a miss is infinitely far off."""
    out = {}
    for seed, df in tables.items():
        x = df[column].to_numpy(dtype=float)
        out[seed] = np.where(np.isnan(x), np.inf, x)
    return out


def cluster_bootstrap(
    a: dict[int, np.ndarray],
    b: dict[int, np.ndarray],
    stat,
    clusters: np.ndarray,
    replicates: int,
    seed: int = 0,
) -> tuple[float, float, float]:
    """Mean paired difference ``stat(a) - stat(b)`` over seeds, and the 2.5 / 97.5 percentiles
    of replicates that draw the seeds and the clusters of instances (every instance of a drawn
    cluster) with replacement. On the synthetic test set each instance is its own cluster (the
    two-level bootstrap of the paper's claims); on the real frames a cluster is an object pose
    (:func:`cloudpose.report.real.object_pose`): the 264 instances are 17 poses seen many
    times, not independent draws. One seed: the instances' interval only."""
    seeds = sorted(a)
    xa = np.stack([a[s] for s in seeds])
    xb = np.stack([b[s] for s in seeds])
    _, inverse = np.unique(clusters, return_inverse=True)
    order = np.argsort(inverse, kind="stable")
    units = np.split(order, np.flatnonzero(np.diff(inverse[order])) + 1)
    mean = float(np.mean(stat(xa) - stat(xb)))
    rng = np.random.default_rng(seed)
    draws = np.empty(replicates)
    for r in range(replicates):
        idx = np.concatenate([units[i] for i in rng.integers(0, len(units), len(units))])
        pick = rng.integers(0, len(seeds), len(seeds))
        draws[r] = float(np.mean(stat(xa[pick][:, idx]) - stat(xb[pick][:, idx])))
    low, high = np.quantile(draws, [0.025, 0.975])
    return mean, float(low), float(high)


def measure(preset: str, runs: dict[float, dict[int, RunRecord]], replicates: int) -> pd.DataFrame:
    """One row per (setting, set, stage, figure): each seed's value without a setting and
    with it, and the paired difference with its interval (percentage points)."""
    base = runs.get(NONE, {})
    rows = []
    for label in sorted(s for s in runs if s != NONE):
        seeds = sorted(set(runs[label]) & set(base))
        if not seeds:
            continue
        a_runs = {s: runs[label][s] for s in seeds}
        b_runs = {s: base[s] for s in seeds}
        for name, set_label in SETS:
            ta, tb = _tables(a_runs, name), _tables(b_runs, name)
            first = next(iter(ta.values()))
            for t in [*ta.values(), *tb.values()]:
                if not first[["frame_id", "instance"]].equals(t[["frame_id", "instance"]]):
                    raise ValueError(f"{preset}: the runs' eval/{name} tables differ in instances")
            clusters = object_pose(first) if name == "real" else np.arange(len(first))
            for prefix, stage in STAGES:
                for figure, column, stat in FIGURES:
                    xa = _column(ta, prefix + column)
                    xb = _column(tb, prefix + column)
                    mean, low, high = cluster_bootstrap(xa, xb, stat, clusters, replicates)
                    how = "object poses x seeds" if name == "real" else "instances x seeds"
                    per_seed = "; ".join(
                        f"{100 * stat(xb[s][None])[0]:.1f} -> {100 * stat(xa[s][None])[0]:.1f}"
                        for s in seeds
                    )
                    rows.append(
                        dict(
                            preset=preset,
                            setting=label,
                            seeds=" ".join(map(str, seeds)),
                            set=set_label,
                            stage=stage,
                            figure=figure,
                            per_seed=per_seed,
                            difference=100 * mean,
                            low=100 * low,
                            high=100 * high,
                            interval=how,
                        )
                    )
    return pd.DataFrame(rows)


STRESS_FIGURES = (  # stress summary column, stage, scale, heading
    ("trans_median_mm", "net", 1.0, "median translation (mm)"),
    ("trans_median_mm", "icp", 1.0, "+ ICP"),
    ("trans_lt_1cm", "net", 100.0, "translation < 1 cm (%)"),
    ("rot_sym_lt_10deg", "net", 100.0, "rot < 10 deg mod sym (%)"),
    ("ads_auc", "net", 100.0, "ADS AUC"),
    ("ads_auc", "icp", 100.0, "+ ICP"),
)


def stress_rows(sweeps: list[Path], folders: dict[str, tuple], perturbation: str) -> pd.DataFrame:
    """The summaries of ``perturbation`` in each ``cloudpose stress`` results folder, one per
    (source, level, stage) and network, with the (preset, setting, seed) of the run whose
    checkpoint the sweep evaluated (matched by the run id the sweep kept, else by the run's
    folder name)."""
    frames = []
    for folder in sweeps:
        sweep = json.loads((folder / "sweep.json").read_text())
        table = collect(folder)
        for method, spec in sweep["methods"].items():
            checkpoint = spec.get("checkpoint")
            if not checkpoint:
                continue
            key = folders.get(spec.get("run_id", "")) or folders.get(Path(checkpoint).parent.name)
            if key is None:
                raise ValueError(
                    f"{folder}/sweep.json: method {method} evaluated {checkpoint}, which is "
                    "none of the runs found (check --preset and the MLflow store)"
                )
            part = table[(table["method"] == method) & (table["perturbation"] == perturbation)]
            frames.append(part.assign(preset=key[0], setting=key[1], seed=key[2]))
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


STRESS_KEY = ["preset", "setting", "seed", "method", "source", "perturbation", "level", "stage"]
"""What makes a row of the stress summaries one curve point of one run."""


def merge_stress(kept: list[pd.DataFrame], swept: pd.DataFrame, perturbation: str) -> pd.DataFrame:
    """Stress summaries read back from earlier ``*_stress.csv`` files (``kept``) with those of
    the sweeps given now (``swept``), ``perturbation`` only: a row of ``swept`` replaces a kept
    one with the same :data:`STRESS_KEY`."""
    frames = []
    for table in kept:
        missing = sorted(set(STRESS_KEY) - set(table.columns))
        if missing:
            raise ValueError(f"a --stress-csv lacks the columns {missing}: not this script's CSV")
        frames.append(table[table["perturbation"] == perturbation])
    frames = [f for f in [*frames, swept] if not f.empty]
    if not frames:
        return pd.DataFrame()
    rows = pd.concat(frames, ignore_index=True)
    rows["level"] = rows["level"].astype(float).round(6)
    rows["seed"] = rows["seed"].astype(int)
    return rows.drop_duplicates(subset=STRESS_KEY, keep="last").reset_index(drop=True)


def stress_markdown(rows: pd.DataFrame, perturbation: str) -> list[str]:
    """Per preset and setting: each level and source, the mean over the seeds swept both
    without a setting and with it, none -> the setting."""
    lines: list[str] = []
    for preset, at_preset in rows.groupby("preset", sort=False):
        base = at_preset[at_preset["setting"] == NONE]
        for label in sorted(s for s in at_preset["setting"].unique() if s != NONE):
            top = at_preset[at_preset["setting"] == label]
            seeds = sorted(set(base["seed"]) & set(top["seed"]))
            if not seeds:
                continue
            lines += [
                "",
                f"## {preset}: under {perturbation}, {label} against none "
                f"(seeds {' '.join(map(str, seeds))}; mean over seeds, none -> {label})",
                "",
                "| source | level | " + " | ".join(h for *_, h in STRESS_FIGURES) + " |",
                "|---|---:|" + "---:|" * len(STRESS_FIGURES),
            ]
            for (source, level), _ in base.groupby(["source", "level"]):
                cells = []
                for column, stage, scale, _h in STRESS_FIGURES:
                    pair = []
                    for side in (base, top):
                        sel = side[
                            (side["source"] == source)
                            & (side["level"] == level)
                            & (side["stage"] == stage)
                            & side["seed"].isin(seeds)
                        ]
                        pair.append(scale * sel[column].mean() if len(sel) else math.nan)
                    cells.append(f"{pair[0]:.1f} -> {pair[1]:.1f}")
                lines.append(f"| {source} | {level:g} | " + " | ".join(cells) + " |")
    return lines


PLOT_FIGURES = (  # column, stage, scale, axis label
    ("trans_median_mm", "net", 1.0, "median translation, network (mm)"),
    ("ads_auc", "icp", 100.0, "ADS AUC, network + ICP"),
)


def stress_plot(
    rows: pd.DataFrame, perturbation: str, path: Path, real_level: float | None = None
) -> None:
    """Per source, the median translation and the ADS AUC after ICP against the level: one
    line per preset and setting, the mean over its swept seeds; ``real_level`` (where the real
    frames sit on this axis) as a dashed line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sources = list(dict.fromkeys(rows["source"]))
    fig, axes = plt.subplots(
        len(PLOT_FIGURES), len(sources), figsize=(5 * len(sources), 7), squeeze=False
    )
    for (preset, label), part in rows.groupby(["preset", "setting"], sort=True):
        seeds = sorted(part["seed"].unique())
        name = f"{preset}, {label} (seeds {' '.join(map(str, seeds))})"
        for col, source in enumerate(sources):
            for row, (column, stage, scale, ylabel) in enumerate(PLOT_FIGURES):
                sel = part[(part["source"] == source) & (part["stage"] == stage)]
                curve = sel.groupby("level")[column].mean() * scale
                ax = axes[row][col]
                ax.plot(curve.index, curve.to_numpy(), marker="o", label=name)
                ax.set_xlabel(f"{perturbation} level")
                ax.set_ylabel(ylabel)
                ax.set_title(source)
                ax.grid(alpha=0.3)
    if real_level is not None:
        for ax in axes.ravel():
            ax.axvline(real_level, ls="--", color="grey", lw=1, label="real frames' level")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()

    def write(tmp: Path) -> None:
        fig.savefig(tmp, dpi=90, format="png")

    atomic_write(path, write, suffix=".png")
    plt.close(fig)


def _pp(x: float) -> str:
    return "–" if math.isnan(x) else f"{x:+.1f}"


def markdown(
    table: pd.DataFrame,
    runs: dict[str, dict[float, dict[int, RunRecord]]],
    argv,
    stress: list[str] = (),
) -> str:
    lines = [
        "# Synthesis settings: each against the same runs without it",
        "",
        f"_made by `python {' '.join(shlex.quote(a) for a in argv)}` in the project folder "
        "that holds the runs; see the script's docstring for what is compared._",
        "",
        "Cells: per seed, the figure without a setting -> with it (%), then the mean paired "
        "difference in percentage points with its 95% interval: a bootstrap that redraws "
        "the seeds together with the test instances (synthetic) or with the 17 object poses "
        "(real; each pose is one object seen in up to 20 frames). The synthetic test set has "
        "neither setting; the real development frames have what the sensor and labels give.",
        "",
        "Runs:",
        "",
    ]
    for preset, by_setting in runs.items():
        for label in sorted(by_setting):
            names = ", ".join(
                f"seed {s} `{by_setting[label][s].run_id[:8]}`" for s in sorted(by_setting[label])
            )
            lines.append(f"- {preset}, {label}: {names}")
    for (preset, label), part in table.groupby(["preset", "setting"], sort=False):
        lines += [
            "",
            f"## {preset}: {label} against none (seeds {part['seeds'].iloc[0]})",
            "",
            "| set | stage | figure | per seed | difference [95%] |",
            "|---|---|---|---|---:|",
        ]
        for r in part.itertuples():
            lines.append(
                f"| {r.set} | {r.stage} | {r.figure} | {r.per_seed} | "
                f"{_pp(r.difference)} [{_pp(r.low)}, {_pp(r.high)}] |"
            )
    return "\n".join([*lines, *stress]) + "\n"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", action="append", required=True, help="preset (repeatable)")
    p.add_argument("--out", type=Path, required=True, help="Markdown to write (CSV beside it)")
    p.add_argument("--replicates", type=int, default=2000, help="bootstrap replicates")
    p.add_argument(
        "--stress",
        type=Path,
        action="append",
        default=[],
        help="a `cloudpose stress` results folder of one of the runs (repeatable)",
    )
    p.add_argument(
        "--stress-csv",
        type=Path,
        action="append",
        default=[],
        help="a *_stress.csv this script wrote, read back beside --stress (repeatable)",
    )
    p.add_argument("--perturbation", default="dilate", help="the stress perturbation to list")
    p.add_argument(
        "--real-level",
        type=float,
        help="where the real frames sit on the perturbation's axis (reports/PRESET/stress.md)",
    )
    args = p.parse_args(argv)
    client = tracking.setup()
    folders: dict[str, tuple] = {}
    runs = {preset: synthesis_runs(client, preset, folders) for preset in args.preset}
    tables = [measure(preset, by_setting, args.replicates) for preset, by_setting in runs.items()]
    table = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame()
    if table.empty:
        print(
            "no preset has runs both with and without a setting at a common seed", file=sys.stderr
        )
        return 1
    kept = [pd.read_csv(f) for f in args.stress_csv]  # read before the output is written
    stress = merge_stress(
        kept, stress_rows(args.stress, folders, args.perturbation), args.perturbation
    )
    stress_lines = stress_markdown(stress, args.perturbation) if not stress.empty else []
    if not stress.empty:
        atomic_text(
            args.out.with_name(args.out.stem + "_stress.csv"),
            stress.to_csv(index=False, float_format="%.5f"),
        )
        png = args.out.with_name(args.out.stem + "_stress.png")
        stress_plot(stress, args.perturbation, png, args.real_level)
    text = markdown(
        table, runs, ["reports/diagnostics/synthesis_experiments.py", *argv], stress_lines
    )
    atomic_text(args.out, text)
    atomic_text(args.out.with_suffix(".csv"), table.to_csv(index=False, float_format="%.2f"))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Rotation < 10 degrees modulo symmetry under symmetry table 1 and table 2, from the stored runs.

Unpacks the MLflow store of the cpu preset's sweep (``reports/cpu/mlflow-store.tar.xz``, kept in
commit b200bde: ``git show b200bde:reports/cpu/mlflow-store.tar.xz > cpu-store.tar.xz``) into a
temporary folder and, for every logged per-instance table that holds the estimated rotations
(columns ``net_R`` / ``icp_R``), recomputes the rotation error modulo symmetry under both
versions of :mod:`cloudpose.geometry.symmetry` (1: ``symmetries.json``, what every stored run
was trained and measured with; 2: ``symmetries-v2.json``), without and with ICP. Reported: the
share of instances under 10 degrees (a miss counts as a failure), pooled and for the classes
whose entry differs between the tables, and the network's median error on the pudding box, the
gelatin box and the banana.

Methods: the runs the cpu reports are rendered from (``cloudpose.report.runs.load_runs``):
shared-0 and geodesic-plain (every seed), FPFH + RANSAC and point-pair features; and the
diagnostic runs of shared-0 (group ``diagnostics``: 75 epochs, 3x the training frames) that
were evaluated on the same test set. Evaluations: ``eval/test`` (ground-truth masks), the
degraded-mask evaluations of the same frames (``eval/test-degraded-*``) and any real-frame
evaluation (``eval/real*``) found in the store.

The instance tables hold no ground truth, so it is made again: the synthetic test frames are
a pure function of (synth seed, split, index, noise, generator version) and are regenerated in
memory from the runs' data parameters (about 30 s); real frames are read from the packaged
``cloudpose/resources/real_dev``. A check: the table-1 recomputation must reproduce the stored
``net_rot_sym_err_deg`` / ``icp_rot_sym_err_deg`` columns (maximum absolute difference printed
and written). A table logged without the estimated rotations (code before 832ec0d990) keeps
its stored table-1 errors and has no table-2 figure.

Run from the repository root (writes ``reports/diagnostics/symmetry_table.md``)::

    git show b200bde:reports/cpu/mlflow-store.tar.xz > /tmp/cpu-store.tar.xz
    python reports/diagnostics/symmetry_table.py --store /tmp/cpu-store.tar.xz
"""

from __future__ import annotations

import argparse
import hashlib
import tarfile
import tempfile
import warnings
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from cloudpose.conventions import resource_path
from cloudpose.data.ycb import load_classes
from cloudpose.geometry.rigid import rotation_error_deg
from cloudpose.geometry.symmetry import rotation_errors_modulo_symmetry
from cloudpose.store import instances, tracking

REPO = Path(__file__).resolve().parents[2]
STORE = REPO / "reports" / "cpu" / "mlflow-store.tar.xz"
OUT = REPO / "reports" / "diagnostics" / "symmetry_table.md"
PRESET = "cpu"
CHANGED = (
    "008_pudding_box",
    "009_gelatin_box",
    "011_banana",
    "021_bleach_cleanser",
    "037_scissors",
    "051_large_clamp",
    "052_extra_large_clamp",
)
"""The classes whose entry differs between table 1 and table 2."""
MEDIAN_CLASSES = ("008_pudding_box", "009_gelatin_box", "011_banana")
THRESHOLD_DEG = 10.0
NETWORKS = ("shared-0", "geodesic-plain")
BASELINES = {"baseline-fpfh": "FPFH + RANSAC", "baseline-ppf": "point-pair features"}
DERIVED_PARAMS = (
    "data.fingerprint",
    "data.train_segments",
    "data.val_segments",
    "data.synth_version",
)
"""Params that follow from others (left out when naming how a diagnostic run differs)."""


@dataclass
class Evaluation:
    """One per-instance table of one run."""

    method: str
    seed: int
    run_id: str
    name: str  # eval/{name}/instances.csv
    table: pd.DataFrame
    errors: dict = field(default_factory=dict)  # (prefix, table version) -> (M,) degrees
    check: dict = field(default_factory=dict)  # prefix -> (sym diff, plain diff) max abs


# ------------------------------------------------------------------------------ the store


def unpack(store: Path, dest: Path) -> Path:
    with tarfile.open(store, "r:xz") as tar:
        tar.extractall(dest, filter="data")
    if not (dest / "mlflow.db").is_file():
        raise SystemExit(f"{store}: no mlflow.db inside")
    return dest


def artifact_dir(uri: str, root: Path) -> Path:
    """The run's artifact folder inside the unpacked store (the URIs name the machine that
    made them, ``/root/cpwork/mlartifacts/...``)."""
    path = tracking.local_artifact(uri, "")
    if path is None:
        raise SystemExit(f"artifact URI {uri}: not a local store")
    parts = path.parts
    if "mlartifacts" not in parts:
        raise SystemExit(f"artifact URI {uri}: no mlartifacts folder in it")
    return root.joinpath(*parts[parts.index("mlartifacts") :])


def eval_tables(uri: str, root: Path) -> dict[str, Path]:
    """Evaluation name -> instance table (instances.parquet, else instances.csv) of one run
    (validation tables left out)."""
    base = artifact_dir(uri, root) / "eval"
    if not base.is_dir():
        return {}
    return {
        p.parent.name: p
        for p in sorted(base.glob("*/instances.csv")) + sorted(base.glob("*/instances.parquet"))
        if p.parent.name == "test"
        or p.parent.name.startswith("test-degraded")
        or p.parent.name.startswith("real")
    }


def read_table(path: Path) -> pd.DataFrame:
    if path.suffix == ".parquet":
        df = instances.read_table(path)
    else:
        df = pd.read_csv(path, dtype={"net_R": str, "icp_R": str, "frame_id": str})
    for col in ("net_R", "icp_R"):
        if col in df:
            df[col] = df[col].fillna("")
    df["miss"] = df["miss"].astype(str).str.lower().isin(("true", "1"))
    return df


def select_runs(client, root: Path):
    """(method label, seed, run, eval name -> path) of the runs to read, and notes."""
    from cloudpose.report.runs import load_runs

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rs = load_runs(PRESET, client=client)
    out, notes = [], []
    by_id = {}
    for r in rs.records:
        if r.variant in NETWORKS or r.variant in BASELINES:
            label = BASELINES.get(r.variant, f"{r.variant} (cpu preset)")
            by_id[r.run_id] = (label, r)
            out.append((label, r.seed, r.run_id, r.artifact_uri, eval_tables(r.artifact_uri, root)))
    ref = {r.seed: r for r in rs.of("shared-0")}
    if not ref:
        raise SystemExit("no shared-0 run of the cpu preset in the store")
    test_key = {ref[s].params.get("data.fingerprint") for s in ref}
    test_tag = {client.get_run(ref[s].run_id).data.tags.get("eval/test/data") for s in ref} - {None}
    # diagnostic runs of shared-0 evaluated on the same test set, newest per (config, seed)
    seen = set()
    for run in tracking.find_runs(client, variant="shared-0", preset=PRESET):
        tags = run.data.tags
        key = (tags.get("config"), tags.get("seed"))
        if run.info.run_id in by_id or key in seen or tags.get("group") != "diagnostics":
            continue
        if tags.get("eval/test/data") not in test_tag:
            continue
        seen.add(key)
        seed = int(tags["seed"])
        base = ref.get(seed) or next(iter(ref.values()))
        diff = [
            f"{k}={v}"
            for k, v in sorted(run.data.params.items())
            if k not in DERIVED_PARAMS and base.params.get(k) != v and not k.startswith("eval")
        ]
        label = f"shared-0, {', '.join(diff) or 'diagnostic'}"
        out.append(
            (
                label,
                seed,
                run.info.run_id,
                run.info.artifact_uri,
                eval_tables(run.info.artifact_uri, root),
            )
        )
    # real-frame evaluations of the baselines are runs of their own (tag split=real)
    for variant, label in BASELINES.items():
        seen = set()
        for run in tracking.find_runs(client, variant=variant, preset=PRESET):
            if run.data.tags.get("split") != "real" or run.data.tags.get("seed") in seen:
                continue
            seen.add(run.data.tags.get("seed"))
            tables = {
                k: v
                for k, v in eval_tables(run.info.artifact_uri, root).items()
                if k.startswith("real")
            }
            out.append(
                (label, int(run.data.tags["seed"]), run.info.run_id, run.info.artifact_uri, tables)
            )
    if not any(name.startswith("real") for *_, t in out for name in t):
        notes.append(
            "No real-frame evaluation (`eval/real*/instances.csv`, or a baseline run with "
            "split=real) is in this store: the figures of `reports/cpu/real_frames.md` were "
            "logged in another store, so the real development frames are not covered here."
        )
    return out, ref, test_key, notes


# ------------------------------------------------------------------------------ ground truth


def synthetic_test_truth(params: dict[str, str]) -> dict[tuple[str, int], tuple[int, np.ndarray]]:
    """(frame_id, instance) -> (class id, R_gt) of the synthetic test frames of ``params``."""
    from cloudpose.data.synth.frames import _generator, generate_frame

    if params.get("data.root", ""):
        raise SystemExit(
            f"data.root={params['data.root']!r}: only the synthetic default is made again"
        )
    seed = int(params.get("data.synth_seed", 0))
    noise = params.get("data.noise", "True") == "True"
    uniform = params.get("data.uniform_rotation", "False") == "True"
    version = int(params.get("data.synth_version", 1))
    n = int(params["data.test_frames"])
    gen = _generator(version)
    truth = {}
    for i in range(n):
        f = generate_frame("test", i, seed, noise, uniform, gen, version)
        for k, (c, P) in enumerate(zip(f.cls_ids, f.poses, strict=True)):
            truth[(f.frame_id, k)] = (int(c), np.asarray(P[:3, :3], dtype=np.float64))
    return truth


def real_truth(frame_ids) -> dict[tuple[str, int], tuple[int, np.ndarray]]:
    """The same for the packaged real development frames."""
    from cloudpose.data.layout import open_dataset

    ds = open_dataset(resource_path("real_dev"))
    truth = {}
    for fid in sorted(set(frame_ids)):
        f = ds.frame(fid)
        for k, (c, P) in enumerate(zip(f.cls_ids, f.poses, strict=True)):
            truth[(fid, k)] = (int(c), np.asarray(P[:3, :3], dtype=np.float64))
    return truth


# ------------------------------------------------------------------------------ errors


def rotations(col: pd.Series) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3, 3) rotations of a ``net_R`` / ``icp_R`` column (identity where empty), and the
    (M,) mask of empty entries."""
    empty = col.str.strip() == ""
    R = np.tile(np.eye(3), (len(col), 1, 1))
    for i, s in enumerate(col):
        if s.strip():
            R[i] = np.asarray(s.split(), dtype=np.float64).reshape(3, 3)
    return R, empty.to_numpy()


def compute(ev: Evaluation, truth, class_names: list[str]) -> None:
    df = ev.table
    keys = list(zip(df["frame_id"], df["instance"].astype(int), strict=True))
    missing = [k for k in keys if k not in truth]
    if missing:
        raise SystemExit(f"{ev.method} seed {ev.seed} {ev.name}: no ground truth for {missing[:3]}")
    cls_truth = np.array([truth[k][0] for k in keys])
    if not np.array_equal(cls_truth, df["cls_id"].to_numpy()):
        raise SystemExit(f"{ev.method} seed {ev.seed} {ev.name}: class ids differ from the frames'")
    R_gt = np.stack([truth[k][1] for k in keys])
    cls = df["cls_id"].to_numpy()
    for p in ("net", "icp"):
        stored = df[f"{p}_rot_sym_err_deg"].to_numpy(dtype=np.float64)
        stored = np.where(np.isfinite(stored), stored, np.inf)
        if f"{p}_R" not in df:
            ev.errors[(p, 1)] = stored
            continue
        R_est, empty = rotations(df[f"{p}_R"])
        miss = df["miss"].to_numpy() | empty
        for t in (1, 2):
            ev.errors[(p, t)] = rotation_errors_modulo_symmetry(
                cls, R_gt, R_est, class_names, miss, t
            )
        hit = ~miss
        sym = np.abs(ev.errors[(p, 1)][hit] - stored[hit])
        plain = np.abs(
            rotation_error_deg(R_gt[hit], R_est[hit]) - df[f"{p}_rot_err_deg"].to_numpy()[hit]
        )
        ev.check[p] = (float(sym.max(initial=0.0)), float(plain.max(initial=0.0)), int(hit.sum()))


# ------------------------------------------------------------------------------ tables


def share(err: np.ndarray | None) -> float:
    return np.nan if err is None or len(err) == 0 else 100.0 * float(np.mean(err < THRESHOLD_DEG))


def fmt(values: list[float]) -> str:
    v = [x for x in values if np.isfinite(x)]
    if not v:
        return "n/a"
    if len(v) == 1:
        return f"{v[0]:.1f}"
    return f"{np.mean(v):.1f} ± {np.std(v, ddof=1):.1f}"


COLS = [("net", 1), ("net", 2), ("icp", 1), ("icp", 2)]
HEAD = "| method | seeds | n | table 1, no ICP | table 2, no ICP | table 1, ICP | table 2, ICP |"


def block(evs: list[Evaluation], cls: str | None, class_names: list[str]) -> list[str]:
    """One Markdown table: a row per method, the four shares (mean ± sd over seeds)."""
    lines = [HEAD, "|---|---|---:|---:|---:|---:|---:|"]
    by_method = defaultdict(list)
    for ev in evs:
        by_method[ev.method].append(ev)
    for method, group in by_method.items():
        group = sorted(group, key=lambda e: e.seed)
        sel = [
            np.ones(len(e.table), bool) if cls is None else (e.table["class"] == cls).to_numpy()
            for e in group
        ]
        ns = sorted({int(s.sum()) for s in sel})
        cells = []
        for key in COLS:
            cells.append(
                fmt(
                    [
                        share(e.errors[key][s]) if key in e.errors else np.nan
                        for e, s in zip(group, sel, strict=True)
                    ]
                )
            )
        seeds = ",".join(str(e.seed) for e in group)
        n = "/".join(map(str, ns))
        lines.append(f"| {method} | {seeds} | {n} | " + " | ".join(cells) + " |")
    return lines


def medians(evs: list[Evaluation]) -> list[str]:
    lines = [
        "| network | seeds | class | n (all seeds) | table 1, no ICP | table 2, no ICP "
        "| table 1, ICP | table 2, ICP |",
        "|---|---|---|---:|---:|---:|---:|---:|",
    ]
    by_method = defaultdict(list)
    for ev in evs:
        if not ev.method.startswith(tuple(BASELINES.values())):
            by_method[ev.method].append(ev)
    for method, group in by_method.items():
        for cls in MEDIAN_CLASSES:
            cells = []
            for key in COLS:
                if not all(key in e.errors for e in group):
                    cells.append("n/a")
                    continue
                v = np.concatenate(
                    [e.errors[key][(e.table["class"] == cls).to_numpy()] for e in group]
                )
                cells.append(f"{np.median(v):.1f}")
            n = sum(int((e.table["class"] == cls).sum()) for e in group)
            seeds = ",".join(str(e.seed) for e in sorted(group, key=lambda e: e.seed))
            lines.append(f"| {method} | {seeds} | {cls} | {n} | " + " | ".join(cells) + " |")
    return lines


def table_differences() -> list[str]:
    """The entries that differ between the tables (checked against :data:`CHANGED`), and how
    far table 2's nearest rotation is from each of table 1's."""
    from cloudpose.geometry.symmetry import load_symmetries

    t1, t2 = load_symmetries(1), load_symmetries(2)

    def same(a, b) -> bool:
        if a.kind != b.kind or len(a.discrete) != len(b.discrete) or a.flip != b.flip:
            return False
        if (a.axis is None) != (b.axis is None):
            return False
        return (a.axis is None or np.allclose(a.axis, b.axis)) and np.allclose(
            a.discrete, b.discrete
        )

    differ = [c for c in t1 if not same(t1[c], t2[c])]
    if set(differ) != set(CHANGED):
        raise SystemExit(f"the tables differ for {differ}, not for {list(CHANGED)} as assumed")
    lines = [
        "| class | table 1 | table 2 | table 2's rotation nearest each of table 1's (deg) |",
        "|---|---|---|---|",
    ]
    for c in CHANGED:
        a, b = t1[c], t2[c]
        off = [
            min(float(rotation_error_deg(S[None], T[None])[0]) for T in b.discrete)
            for S in a.discrete
        ]
        lines.append(
            f"| {c} | {a.describe()} | {b.describe()} | {', '.join(f'{x:.2f}' for x in off)} |"
        )
    return lines


def crossings(evs: list[Evaluation], prefix: str) -> list[str]:
    """Per method and changed class: instances (all seeds) under 10 degrees in table 2 only
    (+) and in table 1 only (-)."""
    lines = ["| method | " + " | ".join(CHANGED) + " |", "|---|" + "---:|" * len(CHANGED)]
    by_method = defaultdict(list)
    for ev in evs:
        if (prefix, 2) in ev.errors:
            by_method[ev.method].append(ev)
    for method, group in by_method.items():
        cells = []
        for cls in CHANGED:
            gained = lost = 0
            for e in group:
                sel = (e.table["class"] == cls).to_numpy()
                ok1 = e.errors[(prefix, 1)][sel] < THRESHOLD_DEG
                ok2 = e.errors[(prefix, 2)][sel] < THRESHOLD_DEG
                gained += int((ok2 & ~ok1).sum())
                lost += int((ok1 & ~ok2).sum())
            cells.append(f"+{gained} -{lost}")
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return lines


def render(evs: list[Evaluation], notes: list[str], store: Path, data: str, class_names) -> str:
    digest = hashlib.sha256(store.read_bytes()).hexdigest()[:12]
    try:
        shown = store.relative_to(REPO)
    except ValueError:
        shown = store
    cmd = "python reports/diagnostics/symmetry_table.py" + (
        "" if store == STORE else f" --store {store}"
    )
    out = [
        "# Rotation error < 10° modulo symmetry: symmetry table 1 against table 2",
        "",
        f"_made by `{cmd}` from the MLflow store `{shown}` (sha256 {digest}); preset {PRESET}, "
        f"data {data[:10]}; ground truth regenerated from the runs' synthetic-data parameters_",
        "",
        "Percent of instances with rotation error < 10° modulo the symmetries of table 1 "
        "(`symmetries.json`, what the runs were trained and measured with) or table 2 "
        "(`symmetries-v2.json`), without and with ICP; a miss counts as a failure. Several seeds: "
        "mean ± sample std over seeds; n: instances per seed. Table 2 differs from table 1 only "
        f"for {', '.join(CHANGED)}; every other class has the same entry, so a pooled "
        "difference comes from these classes alone. 'n/a': the run's instance table was logged "
        "without the estimated rotations (code before 832ec0d990), so only its stored table-1 "
        "errors exist.",
        "",
    ]
    for note in notes:
        out += [f"**Note.** {note}", ""]
    out += [
        "## What differs between the tables",
        "",
        "A half-turn of table 1 is not always one of table 2: table 2 takes the pudding and "
        "gelatin boxes' axes from the principal axes of the points, a few degrees off the model "
        "axis table 1 turns about, so an estimate near table 1's half-turn can be within 10° "
        "under table 1 and not under table 2 (the '-' counts below).",
        "",
        *table_differences(),
        "",
    ]
    # the reproduction check
    out += [
        "## Check: table 1 recomputed against the stored errors",
        "",
        "| method | seed | evaluation | instances with a pose (net / ICP) | max abs diff, "
        "rot sym err (net / ICP), deg | max abs diff, plain rot err (net / ICP), deg |",
        "|---|---:|---|---:|---:|---:|",
    ]
    for ev in evs:
        if not ev.check:
            out.append(f"| {ev.method} | {ev.seed} | {ev.name} | no poses logged | - | - |")
            continue
        n = " / ".join(str(ev.check[p][2]) for p in ("net", "icp"))
        sym = " / ".join(f"{ev.check[p][0]:.2e}" for p in ("net", "icp"))
        plain = " / ".join(f"{ev.check[p][1]:.2e}" for p in ("net", "icp"))
        out.append(f"| {ev.method} | {ev.seed} | {ev.name} | {n} | {sym} | {plain} |")
    out.append("")
    severity = {"mild": 0, "medium": 1, "strong": 2}
    names = sorted(
        {ev.name for ev in evs},
        key=lambda n: (n != "test", n.startswith("real"), severity.get(n.rsplit("-", 1)[-1], 3), n),
    )
    for name in names:
        group = [ev for ev in evs if ev.name == name]
        title = {
            "test": "Test set, ground-truth masks (150 synthetic frames)",
        }.get(name, f"Evaluation `{name}`")
        if name.startswith("test-degraded"):
            title = f"Test set, degraded masks (`{name}`, the same frames and instances)"
        elif name.startswith("real"):
            title = f"Real development frames (`{name}`)"
        out += [f"## {title}", "", "### Pooled (every class)", ""]
        out += [*block(group, None, class_names), ""]
        for cls in CHANGED:
            out += [f"### {cls}", "", *block(group, cls, class_names), ""]
        out += [
            "### Median rotation error of the networks (degrees, instances of all seeds pooled)",
            "",
        ]
        out += [*medians(group), ""]
        for prefix, what in (("net", "without ICP"), ("icp", "with ICP")):
            rows = crossings(group, prefix)
            if len(rows) > 2:
                out += [
                    f"### Instances that change sides of 10°, {what} (all seeds summed): "
                    "+ under 10° in table 2 only, - in table 1 only",
                    "",
                    *rows,
                    "",
                ]
    return "\n".join(out)


def _rank(method: str) -> int:
    """Networks of the cpu preset, then the diagnostic networks, then the baselines."""
    if method.endswith("(cpu preset)"):
        return 0 if method.startswith("shared-0") else 1
    return 3 if method in BASELINES.values() else 2


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", type=Path, default=STORE, help="the store tarball")
    ap.add_argument("--out", type=Path, default=OUT, help="the Markdown file to write")
    args = ap.parse_args()
    store = args.store.resolve()
    if not store.is_file():
        raise SystemExit(
            f"--store {args.store}: no such file; the cpu sweep's store is in commit b200bde: "
            f"git show b200bde:reports/cpu/mlflow-store.tar.xz > {args.store}"
        )
    import mlflow

    class_names = load_classes(resource_path("classes.txt"))
    with tempfile.TemporaryDirectory(prefix="symmetry-table-") as tmp:
        root = unpack(store, Path(tmp))
        client = mlflow.MlflowClient(tracking_uri=f"sqlite:///{root / 'mlflow.db'}")
        runs, ref, data, notes = select_runs(client, root)
        params = next(iter(ref.values())).params
        print("regenerating the synthetic test frames ...", flush=True)
        test_truth = synthetic_test_truth(params)
        evs = []
        for label, seed, run_id, _uri, tables in runs:
            for name, path in tables.items():
                df = read_table(path)
                for c, n in zip(df["cls_id"], df["class"], strict=True):
                    if class_names[int(c) - 1] != n:
                        raise SystemExit(f"{path}: class {c} is {n}, classes.txt says otherwise")
                truth = real_truth(df["frame_id"]) if name.startswith("real") else test_truth
                ev = Evaluation(label, seed, run_id, name, df)
                compute(ev, truth, class_names)
                evs.append(ev)
                chk = (
                    "; ".join(
                        f"{p}: max |table-1 recomputed - stored| {ev.check[p][0]:.2e} deg "
                        f"(plain {ev.check[p][1]:.2e})"
                        for p in ev.check
                    )
                    or "no poses logged"
                )
                print(f"{label} seed {seed} {name}: {len(df)} instances; {chk}", flush=True)
        evs.sort(key=lambda e: (_rank(e.method), e.method, e.seed, e.name))
        text = render(evs, notes, store, next(iter(data)) or "", class_names)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text + "\n", encoding="utf-8")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

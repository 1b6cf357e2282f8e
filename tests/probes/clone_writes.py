"""Run the commands a user runs in a fresh clone, and check that none changes a tracked file, or
leaves a file git does not ignore, without naming it in its output.

Each probe runs in the same clone (``git clone`` of this checkout's HEAD, the package imported
from the clone, this checkout's ``.venv``); between probes the clone is reset (``git checkout``
and ``git clean`` of what git does not ignore, so the committed store unpacked under
``stores/`` is kept). A path counts as named when its path relative to the clone, or its
absolute path, or the absolute path of the folder it says it wrote into, appears in what the
command printed. Prints one line a probe and exits 1 when a
probe changed a file it did not name; writes nothing outside a temporary folder.

    python tests/probes/clone_writes.py            # the probes below (~15 min on 2 cores)
    python tests/probes/clone_writes.py --only predict ship-smoke
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
FRAME = "cloudpose/resources/real_dev/data/0000/000001"

PROBES: dict[str, tuple[list[str], dict[str, str]]] = {
    # name: (command line run in the clone, environment added)
    "help": (["cloudpose", "--help"], {}),
    "ablate-plan": (["make", "ablation-shared", "DRY=1"], {}),
    "report-empty-store": (
        ["cloudpose", "report", "--no-mlflow"],
        {"MLFLOW_TRACKING_URI": "sqlite:///{tmp}/EMPTY.db"},
    ),
    "real-report-empty-store": (
        ["cloudpose", "real-report"],
        {"MLFLOW_TRACKING_URI": "sqlite:///{tmp}/EMPTY.db"},
    ),
    "occlusion-report": (["make", "occlusion-report"], {}),
    "report": (["cloudpose", "report"], {}),
    "real-report": (["cloudpose", "real-report"], {}),
    "ship-smoke": (["cloudpose", "ship", "--run", "shared-0/smoke/seed1"], {}),
    "predict": (
        [
            "cloudpose",
            "predict",
            "--depth",
            f"{FRAME}-depth.png",
            "--label",
            f"{FRAME}-label.png",
            "--color",
            f"{FRAME}-color.png",
            "--checkpoint",
            "pretrained",
            "--overlay",
            "overlay.png",
        ],
        {},
    ),
    "stress-report": (
        [
            "cloudpose",
            "stress",
            "--steps",
            "report",
            "--results",
            "reports/cpu-online/stress-results.tar.xz",
            "--no-progress",
        ],
        {},
    ),
    "mlflow-ui": (["cloudpose", "mlflow-ui", "--no-serve"], {}),
    "store-unpack": (
        ["cloudpose", "store-unpack", "reports/cpu-online/mlflow-store", "--into", "{tmp}/x"],
        {},
    ),
}


def _status(clone: Path) -> set[str]:
    """Paths git reports as changed or not ignored in the clone."""
    out = subprocess.run(
        ["git", "status", "--porcelain=v1", "-uall", "--no-renames"],
        cwd=clone, capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    return {line[3:].strip('"') for line in out.splitlines() if line.strip()}


def _reset(clone: Path) -> None:
    subprocess.run(["git", "checkout", "-q", "--", "."], cwd=clone, check=True)
    subprocess.run(["git", "clean", "-fdq"], cwd=clone, check=True)


def _named(clone: Path, path: str, said: str) -> bool:
    """Whether the output names ``path`` (relative or absolute), or by its absolute path a folder
    holding it (the folder a command says it wrote into)."""
    printed = set(said.split())
    folders = [clone / n for n in Path(path).parents][:-1]  # the clone itself names nothing
    return path in said or str(clone / path) in said or any(str(f) in printed for f in folders)


def probe(clone: Path, tmp: Path, name: str) -> tuple[int, float, list[str], list[str]]:
    """(exit status, seconds, paths changed, those of them the output does not name)."""
    argv, extra = PROBES[name]
    argv = [a.replace("{tmp}", str(tmp)) for a in argv]
    env = {**os.environ, "PYTHONPATH": str(clone), "PATH": f"{REPO / '.venv' / 'bin'}:"
           + os.environ.get("PATH", "")}  # fmt: skip
    env.pop("MLFLOW_TRACKING_URI", None)
    env.update({k: v.replace("{tmp}", str(tmp)) for k, v in extra.items()})
    before = _status(clone)
    t0 = time.perf_counter()
    done = subprocess.run(argv, cwd=clone, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    said = done.stdout + done.stderr
    changed = sorted(_status(clone) - before)
    unnamed = [p for p in changed if not _named(clone, p, said)]
    (tmp / f"{name}.log").write_text(f"$ {' '.join(argv)}\n{said}")
    return done.returncode, seconds, changed, unnamed


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", choices=sorted(PROBES), help="run only these probes")
    ap.add_argument("--keep", action="store_true", help="keep the clone and the logs")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="clone-writes-"))
    clone = tmp / "clone"
    subprocess.run(["git", "clone", "-q", "--local", str(REPO), str(clone)], check=True)
    (clone / ".venv").symlink_to(REPO / ".venv")  # ignored by git: the same environment
    bad = 0
    try:
        for name in args.only or PROBES:
            rc, seconds, changed, unnamed = probe(clone, tmp, name)
            verdict = "ok" if not unnamed else f"CHANGED WITHOUT NAMING: {', '.join(unnamed)}"
            print(f"{name:26s} rc={rc:<3d} {seconds:6.0f} s  {len(changed)} changed  {verdict}")
            bad += bool(unnamed)
            _reset(clone)
    finally:
        if args.keep:
            print(f"clone and logs kept in {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())

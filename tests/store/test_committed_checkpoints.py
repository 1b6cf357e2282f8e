"""What the committed stores cost a clone: a checkpoint is kept only where a committed report
or the shipped network needs it (reports/README.md states the clone's size)."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
REPORTS = ROOT / "reports"
CITING = (".md", ".json", ".csv", ".toml")


def _kept_checkpoints() -> dict[str, list[Path]]:
    """Run id -> its checkpoint files in the committed compact stores."""
    kept: dict[str, list[Path]] = {}
    for pt in sorted(REPORTS.glob("*/mlflow-store/runs/*/artifacts/*.pt")):
        kept.setdefault(pt.parents[1].name, []).append(pt)
    return kept


def _citing_text() -> str:
    """Every committed report's text (the stores themselves aside) and the package's
    resources (the shipped network's record)."""
    parts = []
    for root in (REPORTS, ROOT / "cloudpose" / "resources"):
        for f in sorted(root.rglob("*")):
            if f.suffix in CITING and "mlflow-store" not in f.parts and f.is_file():
                parts.append(f.read_text(errors="replace"))
    return "\n".join(parts)


def test_every_committed_checkpoint_is_cited_by_a_report_or_is_the_shipped_one():
    kept = _kept_checkpoints()
    assert kept, "no checkpoint in the committed stores: the shipped network's run keeps one"
    text = _citing_text()
    uncited = sorted(run for run in kept if run[:8] not in text)
    assert not uncited, (
        f"checkpoints no committed report cites (each costs a clone ~5-7 MB): {uncited}; "
        "repack without them (cloudpose store-pack --checkpoint ...)"
    )

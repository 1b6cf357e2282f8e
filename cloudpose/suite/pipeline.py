"""The pipeline: data -> train -> evaluate, the one place that chains the stages.

Each stage does one thing and receives what it needs: :func:`cloudpose.data.dataset.prepare_data`
makes a config's data (rendering the synthetic default on first use), :func:`cloudpose.train.loop.train`
fits a run on prepared data, :func:`cloudpose.evaluate.evaluate` scores a run. The commands that
chain them (``cloudpose train``, ``cloudpose run``, the ablation runner) call the functions here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from cloudpose import evaluate as evaluation  # by module: the sweep tests replace its functions
from cloudpose.data import dataset
from cloudpose.data.dataset import Prepared
from cloudpose.store import tracking
from cloudpose.train import loop
from cloudpose.train.distributed import SINGLE, World

if TYPE_CHECKING:
    from cloudpose.config import Config
    from cloudpose.evaluate import EvalOutcome
    from cloudpose.train.loop import TrainOutcome

__all__ = ["RunOutcome", "train_and_evaluate", "train_run"]


@dataclass(frozen=True)
class RunOutcome:
    """A trained and evaluated run."""

    train: TrainOutcome
    evaluation: EvalOutcome
    data: Prepared
    real: EvalOutcome | None = None
    """The evaluation on the packaged real development frames (:func:`cloudpose.evaluate.evaluate_real`)."""


def train_run(
    cfg: Config,
    *,
    project_dir: Path | None = None,
    group: str | None = None,
    progress: bool = True,
    data: Prepared | None = None,
    world: World = SINGLE,
    **train_kwargs,
) -> TrainOutcome:
    """Prepare ``cfg``'s data (unless given) and train ``cfg`` on it (resumable); with several
    processes (``world``), rank 0 makes the data before the others read it."""
    project_dir = (project_dir or Path.cwd()).resolve()
    if group is not None:  # before any data is made
        tracking.check_name("group", group)
    if data is None:
        data = world.main_first(
            lambda: dataset.prepare_data(cfg.data, project_dir, progress=progress and world.is_main)
        )
    return loop.train(
        cfg,
        data,
        project_dir=project_dir,
        group=group,
        progress=progress,
        world=world,
        **train_kwargs,
    )


def train_and_evaluate(
    cfg: Config,
    *,
    project_dir: Path | None = None,
    group: str | None = None,
    progress: bool = True,
    data: Prepared | None = None,
    real: bool = True,
) -> RunOutcome:
    """The main job for one config: data, training, evaluation on its own test set and (with
    ``real``) on the real development frames, with and without ICP, all logged to the run."""
    project_dir = (project_dir or Path.cwd()).resolve()
    if group is not None:  # before any data is made
        tracking.check_name("group", group)
    data = data or dataset.prepare_data(cfg.data, project_dir, progress=progress)
    out = train_run(cfg, project_dir=project_dir, group=group, progress=progress, data=data)
    run = str(out.run_dir)
    ev = evaluation.evaluate(run, project_dir=project_dir, progress=progress, own_data=data)
    on_real = (
        evaluation.evaluate_real(run, project_dir=project_dir, progress=progress) if real else None
    )
    return RunOutcome(out, ev, data, on_real)

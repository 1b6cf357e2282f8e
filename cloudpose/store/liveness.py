"""Which runs left RUNNING are dead: one rule for every place that asks.

A run's process may be gone (killed, the machine lost) while MLflow still shows the run
RUNNING. A training process holds its run folder's lock from before it marks the run RUNNING
until after it ends it (:func:`cloudpose.store.runs.run_lock`), and the system releases the
lock of a process that dies (``kill -9`` included): a RUNNING run whose folder (the one whose
``run.json`` names it) is on this machine with its lock file held by no process is dead at
once. Without such a folder to ask (a run of another machine, a run that holds no lock), a run
is dead when a later run of the same config started after its last activity, or when it logged
nothing for :data:`STALE_AFTER_S`. The MLflow UI's preparation
(:func:`cloudpose.report.ui.mark_dead`, through the MLflow client) and store-pack
(:func:`cloudpose.archive.pack._mark_dead`, in SQL on the packed copy) both ask
:func:`dead_runs`, over plain values, and mark what it finds KILLED with the tag
:data:`KILLED_TAG` saying why.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

KILLED_TAG = "marked_killed"
"""Tag of a run marked KILLED (by the MLflow UI's preparation or store-pack): why."""

STALE_AFTER_S = 6 * 3600
"""A RUNNING run that logged nothing for this long (and whose folder no process here holds) is
dead: training logs every epoch, an evaluation takes minutes."""


def when(ms: int | None) -> str:
    """A time in ms since the epoch as local ``YYYY-MM-DD HH:MM``."""
    return time.strftime("%Y-%m-%d %H:%M", time.localtime((ms or 0) / 1000))


def dead_reason(
    last_activity_ms: int,
    now_ms: int,
    later_start_ms: int | None = None,
    folder_locked: bool = False,
    stale_after_s: float = STALE_AFTER_S,
    lock_released: bool = False,
) -> str | None:
    """Why a RUNNING run is dead, or None while it may be alive.

    Args:
        last_activity_ms: its start or its last logged metric, whichever is later.
        now_ms: now.
        later_start_ms: the start of a later run of the same variant, preset, seed and config
            (its process abandoned this run), if there is one.
        folder_locked: a process on this machine holds the run folder's lock (it trains).
        stale_after_s: silence after which a run is dead.
        lock_released: the run's folder is on this machine and no process holds its lock
            file (the process that trained it is gone).
    """
    if folder_locked:
        return None
    if lock_released:
        return (
            f"RUNNING, but no process holds its run folder's lock: the process that trained it "
            f"is gone (last activity {when(last_activity_ms)})"
        )
    if later_start_ms is not None and later_start_ms > last_activity_ms:
        return (
            f"RUNNING, but a later run of the same config started {when(later_start_ms)} "
            f"after its last activity ({when(last_activity_ms)})"
        )
    silent_s = (now_ms - last_activity_ms) / 1000
    if silent_s > stale_after_s:
        return (
            f"RUNNING, but nothing logged since {when(last_activity_ms)} "
            f"({silent_s / 3600:.0f} h; a live run logs every epoch)"
        )
    return None


class DeadRun(NamedTuple):
    """A RUNNING run that :func:`dead_reason` finds dead (:func:`dead_runs`)."""

    run: Any
    last_activity_ms: int
    later_start_ms: int | None
    """The latest start of a later run of the same config, if any."""
    why: str
    lock_released: bool = False
    """Found dead because no process holds its run folder's lock."""


def dead_runs(
    runs: Sequence[tuple[Any, str, int | None, tuple]],
    now_ms: int,
    last_activity: Callable[[Any], int],
    locked: Callable[[Any], bool],
    released: Callable[[Any], bool] | None = None,
) -> list[DeadRun]:
    """Each RUNNING run of ``runs`` that :func:`dead_reason` finds dead.

    Args:
        runs: (run, status, start ms, config key: variant, preset, seed, config) of every
            run of the store; the later starts of each config are found among them.
        now_ms: now.
        last_activity: a run's start or its last training metric's time, ms (asked of
            RUNNING runs only).
        locked: whether a process on this machine holds the run's folder lock.
        released: whether the run's folder is on this machine with a lock that no process
            holds (:func:`dead_reason`'s ``lock_released``); None: never asked.
    """
    by_config: dict[tuple, list[int]] = defaultdict(list)
    for _, _, start, config in runs:
        by_config[config].append(start or 0)
    out = []
    for run, status, start, config in runs:
        if status != "RUNNING":
            continue
        last = last_activity(run)
        later = max((s for s in by_config[config] if s > (start or 0)), default=None)
        held = locked(run)
        gone = not held and released is not None and released(run)
        why = dead_reason(last, now_ms, later, held, lock_released=gone)
        if why is not None:
            out.append(DeadRun(run, last, later, why, gone))
    return out

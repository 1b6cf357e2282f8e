"""Pose estimates as a BOP results CSV (:data:`~cloudpose.data.bop.format.CSV_HEADER`), for
bop_toolkit: writing, refusing to overwrite, and checking one."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cloudpose.data.bop.format import (
    CSV_HEADER,
    bop_ids,
    model_origin,
)
from cloudpose.data.synth.surfaces import load_packaged_models
from cloudpose.files import atomic_text


def write_results_csv(
    table,
    path: str | Path,
    method: str = "icp",
    seconds_per_object: float = -1.0,
    models: dict[int, np.ndarray] | None = None,
) -> int:
    """Write an evaluation's poses as a BOP results CSV (:data:`CSV_HEADER`), for bop_toolkit.

    One line per instance with an estimate (misses are left out: BOP counts a target without
    an estimate as a failure): ``scene_id``, ``im_id`` from the frame id, ``obj_id`` = class
    id, ``score`` 1, ``R`` row-major and ``t`` in millimetres in the BOP frame (module doc),
    ``time`` = the image's objects x ``seconds_per_object`` (the evaluation's mean), the same
    on every line of an image, or -1 when not given.

    Args:
        table: an evaluation's instance table (``frame_id``, ``cls_id``, ``miss`` and the
            method's pose columns ``{method}_R`` (9 numbers), ``{method}_t`` (metres)).
        path: CSV to write.
        method: "net" (the network's estimate) or "icp" (after ICP).
        seconds_per_object: mean time per object, seconds; negative = not available.
        models: {class id: (P, 3) toolbox points} that fix the BOP origin; default the
            packaged ones.

    Returns:
        The number of lines written (header excluded).

    Raises:
        ValueError: the table has no poses for ``method`` (an evaluation of an older version,
            or ``icp`` of an evaluation made without ICP).
    """

    cols = [f"{method}_R", f"{method}_t"]
    missing = [c for c in ("frame_id", "cls_id", "miss", *cols) if c not in table]
    if missing:
        raise ValueError(
            f"instance table has no columns {missing}: evaluate the run again (the table "
            f"keeps the poses since this version){' with ICP' if method == 'icp' else ''}"
        )
    models = models or load_packaged_models()
    rows = table[~table["miss"].astype(bool)]
    per_image = rows.groupby("frame_id")["frame_id"].transform("size")
    lines = [CSV_HEADER]
    for (_, r), n in zip(rows.iterrows(), per_image, strict=True):
        scene_id, im_id = bop_ids(r["frame_id"])
        c = int(r["cls_id"])
        R = np.array(str(r[cols[0]]).split(), dtype=np.float64).reshape(3, 3)
        t = np.array(str(r[cols[1]]).split(), dtype=np.float64)
        t_mm = 1000.0 * (t + R @ model_origin(models[c]))
        time = n * seconds_per_object if seconds_per_object >= 0 else -1
        lines.append(
            f"{scene_id},{im_id},{c},1,{' '.join(f'{v:.9g}' for v in R.ravel())},"
            f"{' '.join(f'{v:.6f}' for v in t_mm)},{time:.6g}"
        )
    atomic_text(path, "\n".join(lines) + "\n")
    return len(lines) - 1


def check_results_destination(path: str | Path, force: bool = False) -> Path:
    """``path`` as a place to write a results CSV: not a folder, and not an existing file
    unless ``force`` (ValueError naming it otherwise); checked before any evaluation."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"--bop-csv {path}: is a folder; expected a CSV file to write")
    if path.exists() and not force:
        raise ValueError(f"--bop-csv {path}: exists; pass --force to overwrite it")
    return path


def write_evaluation_csv(evaluation, path: str | Path, icp: bool) -> tuple[int, str]:
    """An evaluation's poses as a checked BOP results CSV: the ICP-refined poses when ``icp``
    (else the network's), timed by the evaluation's mean ms per object (network + ICP).

    Args:
        evaluation: a :class:`cloudpose.evaluate.EvalOutcome` (its ``table``, ``metrics``
            and ``name``).
        path: CSV to write.
        icp: write the poses after ICP.

    Returns:
        (lines written, the method written: "icp" or "net"). Raises ValueError when the file
        fails :func:`check_results_csv`.
    """
    method = "icp" if icp else "net"
    ms = evaluation.metrics[f"{evaluation.name}/net_ms_per_object"]
    if icp:
        ms += evaluation.metrics[f"{evaluation.name}/icp_ms_per_object"]
    n = write_results_csv(evaluation.table, path, method, seconds_per_object=ms / 1000)
    problems = check_results_csv(path)
    if problems:
        raise ValueError(f"{path} fails the BOP format check: {problems[0]}")
    return n, method


def check_results_csv(path: str | Path, rotation_tol: float = 1e-4) -> list[str]:
    """Check a BOP results CSV against the format of bop_toolkit's documentation.

    The rules (``docs/bop_challenge_2019.md`` and bop_toolkit's ``inout.load_bop_results`` /
    ``check_consistent_timings``): the header ``scene_id,im_id,obj_id,score,R,t,time``; 7
    comma-separated fields per line; integer ids (>= 0, obj_id >= 1); a finite score; R = 9
    numbers separated by white space forming a rotation (``|R R^T - I| <= rotation_tol``,
    det +1); t = 3 numbers (millimetres: a pose with |t| under 10 mm or over 10 m reads as
    metres or nonsense); time a number, >= 0 or -1 (not available), the same (within 1 ms) on
    every line of an image.

    Returns:
        The problems, one line each naming the file and line (empty = the file passes).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: results CSV not found")
    lines = path.read_text().splitlines()
    if not lines or lines[0].strip() != CSV_HEADER:
        return [f"{path}, line 1: header {lines[0] if lines else ''!r}, expected {CSV_HEADER!r}"]
    problems: list[str] = []
    times: dict[tuple[int, int], float] = {}
    for no, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        where = f"{path}, line {no}"
        fields = line.split(",")
        if len(fields) != 7:
            problems.append(f"{where}: {len(fields)} comma-separated fields, expected 7")
            continue
        try:
            scene_id, im_id, obj_id = (int(v) for v in fields[:3])
            score = float(fields[3])
            R = np.array(fields[4].split(), dtype=np.float64)
            t = np.array(fields[5].split(), dtype=np.float64)
            time = float(fields[6])
        except ValueError as e:
            problems.append(f"{where}: unparsable field ({e})")
            continue
        if scene_id < 0 or im_id < 0 or obj_id < 1:
            problems.append(f"{where}: ids {scene_id},{im_id},{obj_id}: expected >= 0, obj_id >= 1")
        if not np.isfinite(score):
            problems.append(f"{where}: score {score} is not finite")
        if R.size != 9 or not np.isfinite(R).all():
            problems.append(f"{where}: R has {R.size} numbers, expected 9 finite ones")
        else:
            R = R.reshape(3, 3)
            ortho = float(np.abs(R @ R.T - np.eye(3)).max())
            if ortho > rotation_tol or np.linalg.det(R) < 0:
                problems.append(
                    f"{where}: R is not a rotation (max |R R^T - I| = {ortho:.2g}, det "
                    f"{np.linalg.det(R):.3g})"
                )
        if t.size != 3 or not np.isfinite(t).all():
            problems.append(f"{where}: t has {t.size} numbers, expected 3 finite ones")
        elif not 10.0 <= np.linalg.norm(t) <= 10000.0:
            problems.append(
                f"{where}: |t| = {np.linalg.norm(t):.4g}; expected millimetres (10 mm .. 10 m)"
            )
        if not (time >= 0 or time == -1):
            problems.append(f"{where}: time {time}: expected >= 0 seconds, or -1")
        key = (scene_id, im_id)
        if key in times and abs(times[key] - time) > 0.001:
            problems.append(
                f"{where}: time {time} differs from {times[key]} on an earlier line of scene "
                f"{scene_id} image {im_id}; one time per image"
            )
        times.setdefault(key, time)
    return problems

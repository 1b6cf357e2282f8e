"""The ``cloudpose`` Typer app: its error handling, help layout, shared options and helpers.

The commands register on :data:`app` in the modules of this package (:mod:`cloudpose.cli`
imports them in the order ``--help`` lists them).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated

import click
import typer
from typer.core import TyperGroup


class _Commands(TyperGroup):
    """Every command with one error handler: bad input is one line on stderr, exit 2.

    The library raises ``ValueError`` / ``FileNotFoundError`` / ``FileExistsError`` naming the
    file, field or name and what was expected (:class:`~cloudpose.store.tracking.StoreError` for a
    store that cannot be opened, ``ConnectionError`` for a service such as Ray that cannot be
    reached);
    ``cloudpose --debug ...`` shows the traceback instead.
    """

    def invoke(self, ctx: click.Context):
        from cloudpose.failures import file_system_message, is_file_system_error
        from cloudpose.store.tracking import StoreError

        try:
            return super().invoke(ctx)
        except _CORRUPT as exc:
            # before ValueError: a JSONDecodeError is one, and its text names no file
            message = _corrupt_file_message(exc)
            if _DEBUG:
                if isinstance(exc, EOFError):  # click would print "Aborted." for it
                    raise RuntimeError(message) from exc
                raise
            typer.secho(f"error: {message}", fg=typer.colors.RED, err=True)
            raise typer.Exit(2) from None
        except (ValueError, OSError, StoreError) as exc:
            # OSError: the library's FileNotFoundError / FileExistsError / DiskFullError /
            # ConnectionError messages, and the system's file-system errors (the path, what it
            # means and the option the user gave it by)
            if _DEBUG:
                raise
            if is_file_system_error(exc):
                message = file_system_message(exc, _option_of(exc, type(ctx)))
            else:
                message = " ".join(str(exc).split()) or type(exc).__name__
            typer.secho(f"error: {message}", fg=typer.colors.RED, err=True)
            raise typer.Exit(2) from None

    def get_command(self, ctx: click.Context, cmd_name: str):
        cmd = super().get_command(ctx, cmd_name)
        if cmd is not None:
            _help_layout(cmd, ctx)
        return cmd

    def format_help(self, ctx: click.Context, formatter) -> None:
        _help_layout(self, ctx)
        return super().format_help(ctx, formatter)


def _option_of(exc: OSError, context: type) -> str | None:
    """The option (or argument) of the failed command that gave the path ``exc`` is about:
    the one whose value is that path, a folder holding it, a path through it (a file where
    its folder should be) or a hidden file beside it named after it (``.NAME.*``, a temporary
    file written before the rename); the most specific one; None when no value names it.
    ``context``: the class of the command's context (typer's own click's), found in the
    traceback's frames."""
    import os

    failed = [
        Path(os.path.abspath(os.fsdecode(p)))
        for p in (exc.filename, exc.filename2)
        if isinstance(p, (str, bytes, os.PathLike))
    ]
    ctx = next(
        (
            v
            for f in _traceback_frames(exc)
            for v in f.f_locals.values()
            if isinstance(v, context) and v.parent is not None
        ),
        None,
    )
    if ctx is None or not failed:
        return None
    best: tuple[int, str] | None = None
    for param in ctx.command.params:
        value = ctx.params.get(param.name or "")
        for given in value if isinstance(value, (list, tuple)) else [value]:
            if not isinstance(given, (str, os.PathLike)) or not str(given):
                continue
            g = Path(os.path.abspath(given))
            if any(
                f == g
                or g in f.parents
                or (f in g.parents and not f.is_dir())
                or (f.parent == g.parent and f.name.startswith(f".{g.name}."))
                for f in failed
            ) and (best is None or len(str(g)) > best[0]):
                best = (len(str(g)), _param_name(param))
    return best[1] if best else None


def _param_name(param) -> str:
    """How the user writes ``param``: its long option (``--out``), or an argument's name as
    ``--help`` shows it in capitals (``OUT``)."""
    if param.param_type_name == "option":
        return next((o for o in param.opts if o.startswith("--")), param.opts[0])
    return (param.name or "argument").upper()


def _corrupt_types() -> tuple[type[BaseException], ...]:
    import json
    import lzma
    import pickle
    import zipfile
    import zlib

    return (
        EOFError,
        zipfile.BadZipFile,
        pickle.UnpicklingError,
        json.JSONDecodeError,
        lzma.LZMAError,
        zlib.error,
    )


_CORRUPT = _corrupt_types()
"""What a parser raises on a zero-byte, truncated or garbled file that no reader of the suite
caught. ``EOFError`` among them: the commands read no terminal input, so it never means Ctrl-D
here; left to click it would print "Aborted." (exit 1, even under ``--debug``), naming nothing."""


def _corrupt_file_message(exc: BaseException) -> str:
    """One line for an unreadable file: the file (found in the traceback's frames: the path
    the innermost reader was given), what the parser said, and what to do."""
    from cloudpose.files import why

    debug = "" if _DEBUG else "; --debug shows the traceback"
    frames = _traceback_frames(exc)
    if any(f.f_code.co_filename.endswith(_PIPES) for f in frames):
        return f"a worker process ended early ({why(exc)}){debug}"
    path = _file_in(frames)
    where = f"{path}: " if path is not None else "a file this command reads is "
    return (
        f"{where}unreadable: empty, truncated or garbled ({why(exc)}); a cache (under "
        f"data/cache) can be deleted and is made again, other files need restoring{debug}"
    )


_PIPES = ("multiprocessing/connection.py",)
"""Where an ``EOFError`` means a worker process's pipe closed, not a file."""


def _traceback_frames(exc: BaseException) -> list:
    """The frames of ``exc``'s traceback, innermost first."""
    tb, frames = exc.__traceback__, []
    while tb is not None:
        frames.append(tb.tb_frame)
        tb = tb.tb_next
    return frames[::-1]


def _file_in(frames: list) -> Path | None:
    """The file the failing read was reading: of the frames from the innermost out to the
    innermost of cloudpose's own, the first local that is a path (or an open file's name) of
    an existing file."""
    import io
    import os

    package = str(Path(__file__).resolve().parents[1])
    for frame in frames:
        for value in list(frame.f_locals.values()):
            if isinstance(value, io.IOBase):
                value = getattr(value, "name", None)
            if isinstance(value, str) and (len(value) > 1024 or "\n" in value):
                continue
            if not isinstance(value, (str, os.PathLike)) or not value:
                continue
            try:
                if Path(value).is_file():
                    return Path(value)
            except (OSError, ValueError):
                continue
        if frame.f_code.co_filename.startswith(package):
            break  # outer frames hold other paths: the run's, the project's
    return None


PIPED_HELP_WIDTH = 120
"""Columns of ``--help`` when the output is not a terminal and COLUMNS is unset (rich's
default there, 80, leaves the help column so narrow that it cuts words with an ellipsis)."""


def _help_layout(cmd, ctx: click.Context) -> None:
    """Help as it reads in a terminal, also when piped; flags shown without a value type.

    Typer shows every option's type, flags too (``--debug <bool>``), as if a flag took a
    value; a flag gets an empty metavar here, so its help shows none.
    """
    import os
    import sys

    from typer import rich_utils

    if rich_utils.MAX_WIDTH is None and "COLUMNS" not in os.environ and not sys.stdout.isatty():
        rich_utils.MAX_WIDTH = PIPED_HELP_WIDTH
    for p in cmd.get_params(ctx):
        if getattr(p, "is_flag", False) and p.metavar is None:
            p.metavar = ""


app = typer.Typer(
    cls=_Commands,
    help="Depth-only 6D pose regression on point clouds (Gao et al., ICRA 2020): "
    "synthetic data, training, ICP, evaluation and the paper's ablations.",
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
)

VariantOpt = Annotated[str, typer.Option(help="Variant name (`cloudpose variants` lists them).")]
PresetOpt = Annotated[
    str,
    typer.Option(
        help="Preset (`cloudpose presets` lists them; cloudpose/resources/registry/presets.toml)."
    ),
]
SeedOpt = Annotated[int, typer.Option(help="Training seed.")]
DataOpt = Annotated[
    str,
    typer.Option(
        "--data", help="Dataset root, YCB-Video or BOP ycbv layout; empty = the synthetic default."
    ),
]
DeviceOpt = Annotated[
    str, typer.Option(help="auto (CUDA when available, as in training), cpu or cuda.")
]
ProgressOpt = Annotated[bool, typer.Option("--progress/--no-progress", help="Progress bars.")]
FramesOpt = Annotated[
    str,
    typer.Option(help="With --data: keyframe (BOP: the BOP19 test targets), all, or an image set."),
]
DryRunOpt = Annotated[
    bool, typer.Option("--dry-run", help="Print the plan (frames, runs, time) and stop.")
]
FreshOpt = Annotated[
    bool,
    typer.Option(
        "--fresh",
        help="Train every run anew into the project's own store (./mlflow.db), reusing none "
        "of the committed runs; default: a sweep of a preset the checkout commits reads and "
        "adds to stores/PRESET/ (the committed sweep, unpacked once).",
    ),
]
OutOpt = Annotated[
    Path | None,
    typer.Option(
        help="Reports folder; default reports/PRESET, or runs/reports/PRESET in a checkout that "
        "commits no reports of PRESET.",
        file_okay=False,
    ),
]
SetOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        help="Override one config field, section.field=value (TOML value; repeatable), "
        "e.g. --set model.rotation_input=centred --set train.epochs=3. An override is another "
        "config: its own run folder and MLflow run.",
    ),
]


# --- the refinement: one option, --refine, declared here for every command that refines ------

REFINE_RECIPES = {
    "paper": "the paper's ICP from the estimate, first radius 1 cm",
    "wide": "ICP from 24 starts, the one that agrees best with the frame's depth kept, first "
    "radius 18 cm: the best measured on real frames, docs/ensemble.md",
    "none": "no ICP",
}
"""The recipes ``--refine`` names: paper and wide are :data:`cloudpose.config.REFINEMENTS`."""

REFINE_FIELDS = {
    "starts": "starts=1|12|24|60 (ICP also from the estimate turned by each element of a "
    "rotation group, the best kept; 1: the estimate alone)",
    "select": "select=fitness|depth (how the starts are scored: ICP's fitness, or agreement "
    "with the frame's depth: coverage and free-space violations)",
    "radius": "radius=METRES (ICP's first correspondence distance, 0.01 the paper's; a wider "
    "one adds iterations at the same shrink down to the paper's last radius)",
    "fallback": "fallback=yes|no (keep the network's pose where ICP's fitness is below "
    "icp.fallback_min_fitness)",
}
"""The fields a ``--refine`` part FIELD=VALUE replaces, as its help describes each."""


@dataclasses.dataclass(frozen=True)
class RefineTakes:
    """What one command's ``--refine`` takes: its recipes and fields, the recipe it refines with
    where none is named (None: the run's own ICP), and that default in words."""

    recipes: tuple[str, ...]
    fields: tuple[str, ...]
    default: str | None
    default_words: str


REFINE_TAKES = {
    "evaluate": RefineTakes(
        ("paper", "wide", "none"), ("starts", "select", "radius", "fallback"), None,
        "the run's own ICP (the paper's, as in the ablation tables); another refinement is "
        "logged under a name of its own",
    ),
    "baseline": RefineTakes(
        ("paper", "wide", "none"), ("starts", "select", "radius"), "paper",
        "paper (as in the tables); another refinement is logged under a name of its own",
    ),
    "predict": RefineTakes(
        ("paper", "wide", "none"), ("starts", "select", "radius"), "wide", "wide"
    ),
    "compare": RefineTakes(
        ("paper", "wide"), ("starts", "select", "radius"), "wide",
        "wide (every estimate also gets the paper's ICP)",
    ),
    "showcase": RefineTakes(
        ("paper", "wide"), (), "wide", "wide (every estimate also gets the paper's ICP)"
    ),
    "stress": RefineTakes(("paper",), ("radius",), "paper", "paper (every method refined alike)"),
}  # fmt: skip
"""The commands that refine, and what the ``--refine`` of each takes."""


def _one_of(names) -> str:
    names = list(names)
    return " or ".join([", ".join(names[:-1]), names[-1]]) if len(names) > 1 else names[0]


def _refine_help(takes: RefineTakes) -> str:
    """The help of a command's ``--refine``: one text for every command, listing what it takes."""
    recipes = ", ".join(f"{r} ({REFINE_RECIPES[r]})" for r in takes.recipes)
    text = f"How the poses are refined, a recipe: {recipes}"
    if takes.fields:
        example = "wide,radius=0.05" if "wide" in takes.recipes else "radius=0.18"
        fields = "; ".join(REFINE_FIELDS[f] for f in takes.fields)
        text += (
            "; and, comma-separated, FIELD=VALUE parts, each replacing one field of the recipe "
            f"(of the default where none is named), e.g. {example}: {fields}"
        )
    return f"{text}. Default: {takes.default_words}."


def refine_option(command: str):
    """``--refine`` as ``command`` declares it (``Annotated[str | None, refine_option(...)]``,
    default None): the same name, type and help wording in every command that refines."""
    takes = REFINE_TAKES[command]
    return typer.Option(
        "--refine",
        metavar="RECIPE[,FIELD=VALUE]" if takes.fields else "RECIPE",
        show_default=False,
        help=_refine_help(takes),
    )


@dataclasses.dataclass(frozen=True)
class RefineChoice:
    """A command's ``--refine``, read (:func:`parse_refine`).

    Attributes:
        icp: False for ``none``.
        recipe: the recipe named, else the command's default (None: the run's own).
        fields: ``starts``, ``select`` and ``radius`` of the recipe, each field given replacing
            the recipe's; only the fields given where the default is the run's own ICP.
        fallback: ``fallback=`` (None: not given).
    """

    icp: bool
    recipe: str | None
    fields: dict
    fallback: bool | None = None

    def overrides(self) -> dict:
        """The fields of the ICP settings it changes (the radius as its schedule); none without
        ICP."""
        from cloudpose.refine import settings_overrides

        if not self.icp:
            return {}
        out = settings_overrides(self.fields)
        if self.fallback is not None:
            out["fallback"] = self.fallback
        return out


def spec_parts(option: str, spec: str) -> tuple[list[str], dict[str, str]]:
    """The words and the KEY=VALUE parts of a comma-separated option value (``wide,radius=0.05``:
    ``["wide"], {"radius": "0.05"}``); a key's ``_`` read as ``-``; ``ValueError`` for a key
    given twice."""
    words: list[str] = []
    given: dict[str, str] = {}
    for part in (p.strip() for p in spec.split(",")):
        key, eq, value = part.partition("=")
        if not eq:
            if part:
                words.append(part)
            continue
        key = key.strip().replace("_", "-")
        if key in given:
            raise ValueError(f"{option} {spec!r}: {key} given twice")
        given[key] = value.strip()
    return words, given


_YES, _NO = ("yes", "true", "on", "1"), ("no", "false", "off", "0")


def parse_refine(command: str, spec: str | None) -> RefineChoice:
    """``command``'s ``--refine`` (:data:`REFINE_TAKES`; None: not given), each part checked
    before any work: ``ValueError`` naming ``--refine`` and the part for a recipe or field the
    command does not take, two recipes, a field beside ``none`` (which would ignore it), or a
    value outside its range (starts a start group's size, select a known score, radius one a
    schedule can start from)."""
    from cloudpose.config import START_GROUPS, refinement
    from cloudpose.refine import SELECTIONS, schedule_for

    takes = REFINE_TAKES[command]
    words, given = spec_parts("--refine", spec or "")
    for word in words:
        if word not in takes.recipes:
            one = "one of " if len(takes.recipes) > 1 else ""
            raise ValueError(f"--refine {word!r}: expected {one}{', '.join(takes.recipes)}")
    if len(words) > 1:
        raise ValueError(f"--refine {spec!r}: one recipe at most ({_one_of(takes.recipes)})")
    recipe = words[0] if words else takes.default
    for key in given:
        if key not in takes.fields:
            sets = f"sets {_one_of(takes.fields)}" if takes.fields else "names a recipe only"
            raise ValueError(f"--refine {key}={given[key]}: {command}'s --refine {sets}")
    if recipe == "none" and given:
        parts = ",".join(f"{k}={v}" for k, v in given.items())
        raise ValueError(
            f"--refine {spec}: none is no ICP, for {parts} to set; drop one or the other"
        )
    value: dict = {}
    for key, text in given.items():
        part = f"--refine {key}={text}"
        if key == "fallback":
            if text.lower() not in _YES + _NO:
                raise ValueError(f"{part}: expected yes or no")
            value[key] = text.lower() in _YES
        elif key == "select":
            if text not in SELECTIONS:
                raise ValueError(f"{part}: expected one of {', '.join(SELECTIONS)}")
            value[key] = text
        elif key == "starts":
            if not text.isdigit() or int(text) not in START_GROUPS:
                raise ValueError(f"{part}: expected one of {', '.join(map(str, START_GROUPS))}")
            value[key] = int(text)
        else:  # radius
            try:
                value[key] = float(text)
                schedule_for(value[key])
            except ValueError as exc:
                why = exc if key in value else "expected metres, e.g. 0.18"
                raise ValueError(f"{part}: {why}") from None
    base = takes.default if recipe == "none" else recipe
    fields = refinement(base, value.get("starts"), value.get("select"), value.get("radius"))
    return RefineChoice(recipe != "none", recipe, fields, value.get("fallback"))


def refinement_of(overrides: dict, cfg_icp=None) -> str:
    """The refinement ``overrides`` (:meth:`RefineChoice.overrides`) make of ``cfg_icp`` (an
    ``icp`` config section; None: the defaults), in words, e.g. ``wide: ICP from 24 starts, ...``."""
    from cloudpose.config import describe_refinement
    from cloudpose.refine import ICPSettings

    base = ICPSettings.from_config(cfg_icp) if cfg_icp is not None else ICPSettings()
    s = dataclasses.replace(base, **overrides)
    return describe_refinement(s.starts, s.select, s.max_distance)


def group_names() -> str:
    """The registered ablation groups, for help texts: ``shared, rotation, loss or symmetry``."""
    from cloudpose.registry import groups

    names = list(groups())
    return ", ".join(names[:-1]) + " or " + names[-1] if len(names) > 1 else "".join(names)


_DEBUG = False
"""``--debug``: bad input raises with its traceback instead of the one-line error."""


@app.callback()
def _main(
    debug: Annotated[
        bool, typer.Option("--debug", help="Show the traceback of an error (default: one line).")
    ] = False,
) -> None:
    global _DEBUG
    _DEBUG = debug
    import warnings

    # "warning: message", without the source line that Python prints beneath it
    warnings.formatwarning = lambda message, *args, **kwargs: f"warning: {message}\n"
    from cloudpose import runtime

    runtime.reexec_with_allocator()
    runtime.configure_threads()


def recorded_command(ctx: typer.Context) -> str:
    """The running command as the user gave it (the options they set, in a canonical order):
    the provenance line written beside a report or figure. Read from the command's context, so
    it is the same however the command was started (console script, ``python -m``, a test)."""
    import shlex

    parts = ["cloudpose", *ctx.command_path.split()[1:]]
    for p in ctx.command.params:
        value = ctx.params.get(p.name)
        source = ctx.get_parameter_source(p.name)
        given = source is not None and source.name != "DEFAULT"
        if p.param_type_name != "option" or value is None or not given:
            continue
        if p.is_flag:
            parts.append(p.opts[0] if value else (p.secondary_opts or p.opts)[0])
            continue
        for v in value if p.multiple else [value]:
            parts += [p.opts[0], _shown(v)]
    return shlex.join(parts)


def _shown(value) -> str:
    """An option's value as the provenance line writes it (paths: :func:`tracking.shown_path`;
    the command still runs as written from the same folder)."""
    from cloudpose.store.tracking import shown_path

    return shown_path(value) if isinstance(value, Path) else str(value)


def config_of(variant: str, preset: str, seed: int, data: str = "", sets=None, **train):
    from cloudpose.registry import parse_overrides, resolve

    overrides: dict = parse_overrides(sets)
    if data:
        overrides.setdefault("data", {})["root"] = data
    train = {k: v for k, v in train.items() if v is not None}
    if train:
        overrides.setdefault("train", {}).update(train)
    return resolve(variant, preset, seed, overrides or None)

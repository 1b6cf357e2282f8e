"""The registry: variants, ablation groups and training presets, as data in
``cloudpose/resources/registry/`` (``variants.toml``, ``presets.toml``; the baselines' settings in
``baselines.toml``), applied to the base :class:`~cloudpose.config.Config`.

A variant and a preset each list only the fields they change (a preset may extend another:
:func:`read_presets`). :func:`resolve` applies the preset, then the variant, then explicit
overrides.
"""

from __future__ import annotations

import dataclasses
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from cloudpose.config import _SECTIONS, Config, check_delta
from cloudpose.conventions import resource_path

VARIANTS_FILE = resource_path("registry", "variants.toml")
PRESETS_FILE = resource_path("registry", "presets.toml")
BASELINES_FILE = resource_path("registry", "baselines.toml")

DEFAULT_PRESET = "cpu-online"
"""The preset a command trains and reports when none is named: on-line synthesis, symmetry
table 2 and depth-noise augmentation, ~15 min a run on a 2-core CPU
(``cloudpose/resources/registry/presets.toml``; ``reports/diagnostics/online_training.md`` says why)."""


@dataclass(frozen=True)
class Variant:
    """One registry entry: a name, why it exists, and the fields it changes."""

    name: str
    why: str
    delta: dict[str, dict[str, Any]]

    def describe(self) -> str:
        """``model.shared_layers=3, loss.rotation=l2``; "(base)" for no change."""
        parts = [f"{s}.{k}={v}" for s, fields in self.delta.items() for k, v in fields.items()]
        return ", ".join(parts) or "(base)"


@dataclass(frozen=True)
class Group:
    """An ablation group: one MLflow experiment and one report table."""

    name: str
    members: tuple[str, ...]
    labels: dict[str, str]

    def pick(self, only: Sequence[str] | None = None) -> tuple[str, ...]:
        """The members, or those named in ``only`` (in the group's order); ValueError naming
        any name of ``only`` that is not a member."""
        if not only:
            return self.members
        unknown = [v for v in only if v not in self.members]
        if unknown:
            raise ValueError(
                f"group {self.name!r} has no member {', '.join(map(repr, unknown))}; "
                f"its members: {', '.join(self.members)}"
            )
        return tuple(v for v in self.members if v in set(only))


@cache
def _load_variants() -> tuple[dict[str, Variant], dict[str, Group]]:
    raw = tomllib.loads(VARIANTS_FILE.read_text())
    variants = {}
    for name, entry in raw.get("variant", {}).items():
        entry = dict(entry)
        why = entry.pop("why", "")
        if not why:
            raise ValueError(f"{VARIANTS_FILE}: variant {name!r} has no 'why'")
        variants[name] = Variant(name, why, check_delta(f"{VARIANTS_FILE} [{name}]", entry))
    groups = {}
    for name, entry in raw.get("group", {}).items():
        missing = [m for m in entry["members"] if m not in variants]
        if missing:
            raise ValueError(f"{VARIANTS_FILE}: group {name!r} names unknown variants {missing}")
        groups[name] = Group(name, tuple(entry["members"]), dict(entry.get("labels", {})))
    return variants, groups


def read_presets(path: Path = PRESETS_FILE) -> dict[str, tuple[str, dict[str, dict[str, Any]]]]:
    """Preset name -> (its why, the fields it changes) from a presets file, in file order.

    A preset table may name a base, ``extends = "cpu-online"``: it changes the base's fields
    (resolved the same way, so bases chain) and then its own, which win. Its ``why`` is its own.

    Raises:
        ValueError: naming the file, the preset and the field, for an unknown section or field,
            an ``extends`` that names no preset, or a chain of ``extends`` that comes back to a
            preset it passed (a cycle, listed).
    """
    raw = tomllib.loads(Path(path).read_text())
    own: dict[str, tuple[str | None, str, dict[str, dict[str, Any]]]] = {}
    for name, entry in raw.get("preset", {}).items():
        entry = dict(entry)
        why = entry.pop("why", "")
        base = entry.pop("extends", None)
        if base is not None and not isinstance(base, str):
            raise ValueError(f"{path} [{name}]: extends = {base!r}: expected a preset's name")
        own[name] = (base, why, check_delta(f"{path} [{name}]", entry))
    return {name: (own[name][1], _extended(name, own, path)) for name in own}


def _extended(name: str, own: dict, path: Path) -> dict[str, dict[str, Any]]:
    """The delta of preset ``name`` with every base of its ``extends`` chain under it."""
    chain = [name]
    while (base := own[chain[-1]][0]) is not None:
        if base not in own:
            raise ValueError(
                f"{path} [{chain[-1]}]: extends = {base!r}, which is no preset; "
                f"valid presets: {', '.join(own)}"
            )
        if base in chain:
            cycle = " -> ".join([*chain[chain.index(base) :], base])
            raise ValueError(f"{path} [{chain[-1]}]: extends = {base!r} makes a cycle: {cycle}")
        chain.append(base)
    delta: dict[str, dict[str, Any]] = {}
    for link in reversed(chain):  # the furthest base first, the preset's own fields last
        for section, fields in own[link][2].items():
            delta.setdefault(section, {}).update(fields)
    return delta


@cache
def _load_presets() -> dict[str, tuple[str, dict[str, dict[str, Any]]]]:
    return read_presets(PRESETS_FILE)


def variants() -> dict[str, Variant]:
    """All registered variants by name, in registry order."""
    return _load_variants()[0]


def groups() -> dict[str, Group]:
    """All ablation groups by name."""
    return _load_variants()[1]


def presets() -> dict[str, str]:
    """Preset name -> its one-line why."""
    return {name: why for name, (why, _) in _load_presets().items()}


def get_variant(name: str) -> Variant:
    """The registered variant ``name``; unknown names raise with the list of valid ones."""
    table = variants()
    if name not in table:
        raise ValueError(f"unknown variant {name!r}; valid variants: {', '.join(table)}")
    return table[name]


def get_group(name: str) -> Group:
    """The ablation group ``name``; unknown names raise with the list of valid ones."""
    table = groups()
    if name not in table:
        raise ValueError(f"unknown group {name!r}; valid groups: {', '.join(table)}")
    return table[name]


def groups_of(variant: str) -> list[str]:
    """Names of the groups that list ``variant``."""
    return [g.name for g in groups().values() if variant in g.members]


def _apply(cfg: Config, delta: dict[str, dict[str, Any]]) -> Config:
    changes = {s: dataclasses.replace(getattr(cfg, s), **f) for s, f in delta.items()}
    return dataclasses.replace(cfg, **changes)


def parse_overrides(items: list[str] | None) -> dict[str, dict]:
    """The ``--set`` grammar: ``["train.epochs=3", "data.classes=['011_banana']"]`` ->
    ``{"train": {"epochs": 3}, "data": {"classes": ["011_banana"]}}``, for :func:`resolve`.

    Values are TOML (numbers, true/false, quoted strings, arrays); a bare word is a string.
    """
    out: dict[str, dict] = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        section, dot, name = key.strip().partition(".")
        if not sep or not dot or not name:
            raise ValueError(f"--set {item!r}: expected section.field=value, e.g. train.epochs=3")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()
        out.setdefault(section, {})[name] = value
    return out


def resolve(
    variant: str = "shared-0",
    preset: str = DEFAULT_PRESET,
    seed: int = 1,
    overrides: dict[str, dict[str, Any]] | None = None,
) -> Config:
    """The full config of ``variant`` trained with ``preset`` and ``seed``.

    Order: base defaults, then the preset's delta, then the variant's, then ``overrides``
    (``{"train": {"epochs": 3}}``).
    """
    table = _load_presets()
    if preset not in table:
        raise ValueError(f"unknown preset {preset!r}; valid presets: {', '.join(table)}")
    cfg = Config(variant=variant, preset=preset, seed=seed)
    cfg = _apply(cfg, table[preset][1])
    cfg = _apply(cfg, get_variant(variant).delta)
    if overrides:
        cfg = _apply(cfg, _check_types("overrides", check_delta("overrides", overrides)))
    return cfg


_TYPES = {
    "int": (int,),
    "float": (int, float),
    "str": (str,),
    "bool": (bool,),
    "None": (type(None),),
}


def _check_types(where: str, delta: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """``delta`` if each value has its field's type (``train.epochs`` an integer, ``train.lr``
    a number, a tuple field a list), else ``ValueError`` naming the field."""
    for section, fields in delta.items():
        annotations = {f.name: str(f.type) for f in dataclasses.fields(_SECTIONS[section])}
        for key, value in fields.items():
            kind = annotations[key]
            if kind.startswith("tuple"):
                ok = isinstance(value, list | tuple)
            else:
                parts = [_TYPES.get(p.strip(), (object,)) for p in kind.split("|")]
                allowed = tuple(t for types in parts for t in types)
                ok = isinstance(value, allowed) and (bool in allowed or not isinstance(value, bool))
            if not ok:
                raise ValueError(f"{where}: {section}.{key}={value!r}: expected {kind}")
    return delta

"""The command line as a whole: commands in panels, at most 12 options a command, the
refinement one option alike in every command, help without the package's internals, the named
refinements."""

from __future__ import annotations

import re

import pytest
import typer.main

from cloudpose.cli import PANELS, app
from cloudpose.config import PRODUCT_REFINEMENT, REFINEMENTS, describe_refinement, refinement
from tests.conftest import cli, one_line_error


def _commands() -> dict:
    return typer.main.get_group(app).commands


def test_every_command_is_in_one_panel_and_help_shows_the_panels():
    listed = [name for names in PANELS.values() for name in names]
    assert sorted(listed) == sorted(_commands()), "a command outside PANELS, or a stale name"
    assert len(listed) == len(set(listed))
    res = cli("--help")
    assert res.exit_code == 0
    at = [res.output.index(f"─ {panel} ") for panel in PANELS]
    assert at == sorted(at), "panels out of order"
    for panel, names in PANELS.items():  # each panel lists its commands in its own order
        block = res.output[res.output.index(f"─ {panel} ") :]
        pos = [re.search(rf"│ {re.escape(n)} ", block).start() for n in names]
        assert pos == sorted(pos), (panel, names)


def test_the_refinement_is_one_option_declared_alike_in_every_command_that_refines():
    """Every command that refines takes one --refine (no --icp-* beside it), declared by the
    one helper: the same name, type, metavar and help wording, listing what that command
    takes."""
    from cloudpose.cli.app import REFINE_TAKES, _refine_help

    refining = {}
    for name, cmd in _commands().items():
        opts = {o for p in cmd.params for o in [*p.opts, *p.secondary_opts]}
        assert not [o for o in opts if o.startswith(("--icp", "--no-icp"))], (name, opts)
        for p in cmd.params:
            if "--refine" in p.opts:
                refining[name] = p
    assert set(refining) == set(REFINE_TAKES)
    assert {"evaluate", "predict", "baseline", "compare", "showcase", "stress"} <= set(refining)
    for name, p in refining.items():
        assert p.opts == ["--refine"] and p.default is None, name
        assert not p.is_flag and not p.multiple, name
        assert p.help == _refine_help(REFINE_TAKES[name])
        assert p.help.startswith("How the poses are refined, a recipe: ")
        assert p.metavar == ("RECIPE[,FIELD=VALUE]" if REFINE_TAKES[name].fields else "RECIPE")


def test_no_command_takes_more_than_12_options():
    counts = {
        name: sum(p.param_type_name == "option" for p in cmd.params)
        for name, cmd in _commands().items()
    }
    assert {n: c for n, c in counts.items() if c > 12} == {}


def test_the_stress_help_names_every_perturbation():
    from cloudpose.studies import perturbations as st

    (only,) = [p for p in _commands()["stress"].params if p.name == "only"]
    assert f"({', '.join(st.PERTURBATIONS)})" in only.help
    assert f"({', '.join(st.SOURCES)})" in only.help


def test_no_help_names_the_packages_internals():
    """No module path, source file, private function, docstring markup or "see the package's
    docstring" in any help: what each does, in the user's words."""
    internals = re.compile(
        r"cloudpose\.[a-z_]+\.|\.py\b|\b_[a-z]\w*\(|``|:(func|mod|data|class|meth):|package doc"
    )
    for name, cmd in _commands().items():
        texts = [cmd.help or ""] + [getattr(p, "help", "") or "" for p in cmd.params]
        for text in texts:
            assert not internals.search(text), (name, text)


def test_the_named_refinements_and_their_overrides():
    assert refinement("paper") == {"starts": 1, "select": "fitness", "radius": 0.01}
    assert refinement(PRODUCT_REFINEMENT) == REFINEMENTS["wide"]
    assert refinement("wide", radius=0.05) == {"starts": 24, "select": "depth", "radius": 0.05}
    assert refinement(None, starts=12) == {"starts": 12}
    assert refinement() == {}
    with pytest.raises(ValueError, match=r"--refine 'fast': expected one of paper, wide"):
        refinement("fast")
    assert describe_refinement(**REFINEMENTS["wide"]).startswith("wide: ICP from 24 starts")
    assert describe_refinement(12, "fitness", 0.05) == (
        "ICP from 12 starts, the one that fits best kept, first radius 5 cm"
    )


def test_refine_takes_the_recipe_then_each_field():
    from cloudpose.cli.app import parse_refine
    from cloudpose.refine import schedule_for

    wide = parse_refine("evaluate", "wide")
    assert wide.overrides() == {"starts": 24, "select": "depth", **schedule_for(0.18)}
    assert parse_refine("evaluate", "wide,starts=60").overrides()["starts"] == 60
    assert parse_refine("evaluate", None).overrides() == {}  # the run's own
    assert parse_refine("evaluate", "fallback=yes").overrides() == {"fallback": True}
    assert parse_refine("evaluate", "starts=12").fields == {"starts": 12}
    # where the default is a recipe, a field alone replaces one of its fields
    assert parse_refine("predict", "starts=12").fields == {**REFINEMENTS["wide"], "starts": 12}
    assert parse_refine("stress", "radius=0.18").fields["radius"] == 0.18
    none = parse_refine("predict", "none")
    assert not none.icp and none.overrides() == {}
    assert parse_refine("showcase", None).recipe == PRODUCT_REFINEMENT


@pytest.mark.parametrize(
    ("command", "spec", "needles"),
    [
        ("evaluate", "none,starts=24,radius=0.18", ["none is no ICP", "starts=24,radius=0.18"]),
        ("evaluate", "wide,starts=7", ["--refine starts=7: expected one of 1, 12, 24, 60"]),
        ("evaluate", "paper,wide", ["one recipe at most"]),
        ("evaluate", "starts=24,starts=12", ["starts given twice"]),
        ("evaluate", "fallback=maybe", ["--refine fallback=maybe: expected yes or no"]),
        ("evaluate", "radius=x", ["--refine radius=x: expected metres"]),
        ("predict", "fallback=yes", ["predict's --refine sets starts, select or radius"]),
        ("compare", "none", ["--refine 'none': expected one of paper, wide"]),
        ("showcase", "radius=0.1", ["showcase's --refine names a recipe only"]),
        ("stress", "wide", ["--refine 'wide': expected paper"]),
        ("stress", "starts=24", ["stress's --refine sets radius"]),
    ],
)
def test_a_refinement_a_command_cannot_make_is_refused_naming_the_part(command, spec, needles):
    from cloudpose.cli.app import parse_refine

    with pytest.raises(ValueError) as info:
        parse_refine(command, spec)
    for needle in needles:
        assert needle in str(info.value)


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        ((), REFINEMENTS["paper"]),  # a baseline run keeps the paper's ICP, as the tables do
        (("--refine", "wide"), REFINEMENTS["wide"]),
        (("--refine", "wide,radius=0.05"), {**REFINEMENTS["wide"], "radius": 0.05}),
        (("--refine", "starts=12"), {**REFINEMENTS["paper"], "starts": 12}),
    ],
)
def test_baseline_passes_the_refinement_it_is_given(monkeypatch, args, expected):
    import cloudpose.studies.baseline_runs

    got = {}

    def fake(method, preset, seed, **kw):
        got.update(starts=kw["icp_starts"], select=kw["icp_select"], radius=kw["icp_radius"])
        raise ValueError("stop here")

    monkeypatch.setattr(cloudpose.studies.baseline_runs, "run_baseline", fake)
    monkeypatch.setattr("cloudpose.report.committed.sweep_store", lambda *a: "./mlflow.db")
    res = cli("baseline", "--method", "fpfh", *args, "--no-progress")
    one_line_error(res, "stop here")
    assert got == expected


def test_compare_refines_beside_the_paper_with_the_products_refinement(monkeypatch):
    import cloudpose.studies.compare

    got = {}

    def fake(out, **kw):
        got.update(starts=kw["starts"], select=kw["select"], radius=kw["radius"])
        raise ValueError("stop here")

    monkeypatch.setattr(cloudpose.studies.compare, "run_compare", fake)
    one_line_error(cli("compare", "--no-progress"), "stop here")
    assert got == REFINEMENTS[PRODUCT_REFINEMENT]
    one_line_error(cli("compare", "--refine", "paper,starts=12"), "stop here")
    assert got == {**REFINEMENTS["paper"], "starts": 12}


def test_no_function_of_the_cli_is_over_120_lines():
    import ast
    from pathlib import Path

    import cloudpose.cli

    long = []
    for path in sorted(Path(cloudpose.cli.__file__).parent.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                start = min([node.lineno, *(d.lineno for d in node.decorator_list)])
                if node.end_lineno - start + 1 > 120:
                    long.append(f"{path.name}:{node.name}")
    assert not long, f"split into helpers: {long}"

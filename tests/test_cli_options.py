"""The command line as a whole: commands in panels, the refinement options one set alike in
every command, help without the package's internals, the named refinements."""

from __future__ import annotations

import re

import pytest
import typer.main

from cloudpose.cli import PANELS, app
from cloudpose.config import PRODUCT_REFINEMENT, REFINEMENTS, describe_refinement, refinement
from tests.conftest import cli, one_line_error

REFINE_OPTIONS = ("refine", "icp_starts", "icp_select", "icp_radius", "icp_fallback")


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


def test_the_refinement_options_are_declared_alike_in_every_command():
    import inspect

    declared = {  # every command declares each of them by the one shared annotation
        "refine": "RefineOpt",
        "icp_starts": "IcpStartsOpt",
        "icp_select": "IcpSelectOpt",
        "icp_radius": "IcpRadiusOpt",
        "icp_fallback": "IcpFallbackOpt",
    }
    users: dict[str, list[str]] = {}
    for info in app.registered_commands:
        for name, param in inspect.signature(info.callback).parameters.items():
            if name in REFINE_OPTIONS:
                users.setdefault(name, []).append(info.callback.__name__)
                assert param.annotation == declared[name], (info.callback.__name__, name)
    assert {"evaluate", "predict", "baseline", "compare", "showcase"} <= set(users["refine"])
    assert set(users["refine"]) - {"showcase"} <= set(users["icp_starts"])
    assert "stress" in users["icp_radius"]


def test_no_help_names_the_packages_internals():
    for name, cmd in _commands().items():
        texts = [cmd.help or ""] + [getattr(p, "help", "") or "" for p in cmd.params]
        for text in texts:
            assert not re.search(r"cloudpose\.[a-z_]+\.", text), (name, text)


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


def test_icp_overrides_take_the_recipe_then_each_option():
    from cloudpose.cli.app import icp_overrides
    from cloudpose.refine import schedule_for

    wide = icp_overrides(refine="wide")
    assert wide == {"starts": 24, "select": "depth", **schedule_for(0.18)}
    assert icp_overrides(refine="wide", starts=60)["starts"] == 60
    assert icp_overrides() == {}  # the run's own
    assert icp_overrides(fallback=True) == {"fallback": True}
    with pytest.raises(ValueError, match="--refine --icp-starts with --no-icp"):
        icp_overrides(starts=24, icp=False, refine="wide")
    with pytest.raises(ValueError, match="--icp-starts 7"):
        icp_overrides(refine="wide", starts=7)


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        ((), REFINEMENTS["paper"]),  # a baseline run keeps the paper's ICP, as the tables do
        (("--refine", "wide"), REFINEMENTS["wide"]),
        (("--refine", "wide", "--icp-radius", "0.05"), {**REFINEMENTS["wide"], "radius": 0.05}),
        (("--icp-starts", "12"), {**REFINEMENTS["paper"], "starts": 12}),
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
    one_line_error(cli("compare", "--refine", "paper", "--icp-starts", "12"), "stop here")
    assert got == {**REFINEMENTS["paper"], "starts": 12}

"""Report tables as Markdown, LaTeX and CSV under their provenance line (cloudpose.report.formats)."""

from __future__ import annotations

import io

import numpy as np
import pandas as pd

from cloudpose.report.formats import Provenance, Table

PROV = Provenance(
    "cloudpose report --preset cpu", "cpu", "synth-seed0-v2 (17f7b236b7)", (1, 2), ("abc1234",)
)


def _table() -> Table:
    return Table(
        name="table3_shared_layers",
        title="Shared layers & ADS AUC_x",
        header=[("", "variant"), ("without ICP", "ADS"), ("without ICP", "<1cm"), ("", "params")],
        rows=[
            ["shared-0", "71.2 ± 0.3", "40.1", "1.6M"],
            None,
            ["shared-all", "65.0", "30.5", "0.8M"],
        ],
        data=pd.DataFrame({"variant": ["shared-0", "shared-all"], "ads_auc": [71.23456, 65.0]}),
        notes=["Mean over 2 seeds."],
    )


def test_provenance_line_says_what_made_the_report():
    line = PROV.line()
    assert line == (
        "made by `cloudpose report --preset cpu`; preset cpu; data: synth-seed0-v2 (17f7b236b7); "
        "seeds 1, 2; code abc1234 (git commit of the runs)"
    )
    empty = Provenance("c", "smoke", "d", (), (), renderer="def5678").line()
    assert "seeds none; code none" in empty and empty.endswith("; rendered by code def5678")


def test_markdown_has_the_provenance_grouped_columns_and_right_aligned_numbers():
    md = _table().markdown(PROV).splitlines()
    assert md[0] == "# Shared layers & ADS AUC_x"
    assert md[2] == f"_{PROV.line()}_"
    assert md[4] == "| variant | without ICP (ADS) | without ICP (<1cm) | params |"
    assert md[5] == "|---|---:|---:|---:|"
    assert md[6:8] == [
        "| shared-0 | 71.2 ± 0.3 | 40.1 | 1.6M |",
        "| shared-all | 65.0 | 30.5 | 0.8M |",
    ]
    assert md[-1] == "Mean over 2 seeds."


def test_latex_escapes_text_and_spans_the_column_groups():
    tex = _table().latex(PROV)
    assert tex.startswith(f"% {PROV.line()}\n")
    assert r"\caption{Shared layers \& ADS AUC\_x}" in tex
    assert r"\begin{tabular}{lrrr}" in tex
    assert r" & \multicolumn{2}{c}{without ICP} &  \\" in tex
    assert r"\cmidrule(lr){2-3}" in tex
    assert r"shared-0 & 71.2 $\pm$ 0.3 & 40.1 & 1.6M \\" in tex
    body = tex.split(r"\midrule")
    assert len(body) == 3  # after the header, and the section break the None row makes
    assert tex.rstrip().endswith("% Mean over 2 seeds.")


def test_csv_holds_the_numbers_and_write_makes_all_three(tmp_path):
    text = _table().csv(PROV)
    assert text.splitlines()[0] == f"# {PROV.line()}"
    back = pd.read_csv(io.StringIO(text), comment="#")
    assert back["ads_auc"].tolist() == [71.2346, 65.0]
    paths = _table().write(tmp_path / "cpu", PROV)
    assert [p.name for p in paths] == [f"table3_shared_layers.{e}" for e in ("md", "tex", "csv")]
    assert paths[0].read_text(encoding="utf-8") == _table().markdown(PROV)


def test_a_figure_rendered_again_by_other_code_is_the_same_file(tmp_path):
    from dataclasses import replace

    from cloudpose.report.plots import Series, plot_occlusion

    rng = np.random.default_rng(0)
    table = pd.DataFrame({"occlusion": rng.uniform(0, 1, 50), "net_ads": rng.uniform(0, 0.02, 50)})
    series = [Series("shared-0", [table])]
    a = plot_occlusion(series, tmp_path / "a.png", replace(PROV, renderer="abc1234"), "t")
    b = plot_occlusion(series, tmp_path / "b.png", replace(PROV, renderer="def5678"), "t")
    assert a.read_bytes() == b.read_bytes()
    c = plot_occlusion(series, tmp_path / "c.png", replace(PROV, seeds=(1, 2, 3)), "t")
    assert c.read_bytes() != a.read_bytes()  # the runs' provenance is still drawn

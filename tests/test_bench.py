"""Smoke test of the benchmark harness (benchmarks/run_all.py) in quick mode: it runs, writes
both reports, and every figure carries its value, reference, ratio, target and verdict.
No timing is asserted."""

from __future__ import annotations

import json

import pytest

from benchmarks import bench_train, run_all

FIGURE_KEYS = {"value", "unit", "what", "reference", "ratio", "target", "met"}


def test_quick_run_writes_every_selected_figure(tmp_path):
    names = ["fps", "icp_ms_per_object", "infer", "cpu_variant"]
    report = run_all.run(names, quick=True, out_dir=tmp_path)
    assert not report["errors"]
    saved = json.loads((tmp_path / "benchmarks.json").read_text())
    md = (tmp_path / "benchmarks.md").read_text()
    expected = {
        "fps_ms_20k",
        "icp_ms_per_object",
        "icp_starts24_ms_per_object",
        "ads_ms_per_10k",
        "infer_ms_per_object",
        "infer_ms_frame8",
        "cpu_variant_wall_s",
    }
    assert set(saved["figures"]) == expected
    assert {"machine", "commit", "command", "seconds"} <= set(saved)
    assert saved["machine"]["cpu"]["cores"] >= 1
    for key, fig in saved["figures"].items():
        assert FIGURE_KEYS <= set(fig), key
        assert f"`{key}`" in md
    for key in expected - {"cpu_variant_wall_s"}:
        fig = saved["figures"][key]
        assert fig["value"] > 0 and fig["reference"]["value"] > 0 and fig["ratio"] > 0, key
    # the exactness checks the figures rest on
    sizes = saved["figures"]["fps_ms_20k"]["detail"]
    assert all(
        s["same_indices_as_fpsample"] and s["same_indices_as_numpy_loop"] for s in sizes.values()
    )
    assert saved["figures"]["ads_ms_per_10k"]["detail"]["ads_max_value_difference_m"] < 1e-12
    assert saved["figures"]["icp_ms_per_object"]["detail"]["icp_max_pose_difference"] < 1e-9
    assert saved["figures"]["infer_ms_per_object"]["detail"]["folded_vs_plain_max_abs_diff"] < 1e-4


def test_train_figures_are_mapped_from_bench_train(tmp_path, monkeypatch):
    """The train group turns bench_train.run's result into the two figures (bench_train itself
    takes a minute even in quick mode; its own tests cover it), here on a recorded result."""
    fake = {
        "machine": {},
        "gemm_fp32_gflops": {"peak_gflops": 100.0},
        "train_fraction_of_peak": {
            "value": 0.82,
            "what": "shared-0 fused",
            "samples_per_s": 180.0,
            "plain_samples_per_s": 60.0,
            "plain_fraction_of_peak": 0.28,
            "per_variant": {},
        },
        "train_bf16_samples_per_s": {"value": None, "skipped": "no bf16 hardware"},
        "train_by_allocator": {"tcmalloc": {"plain": 60.0, "fused": 180.0}},
    }
    monkeypatch.setattr(bench_train, "run", lambda quick=False: fake)
    report = run_all.run(["train"], quick=True, out_dir=tmp_path)
    figs = report["figures"]
    assert figs["train_fraction_of_peak"]["met"] is True
    assert figs["train_fraction_of_peak"]["ratio"] == pytest.approx(0.82 / 0.28)
    assert figs["train_bf16_samples_per_s"]["value"] is None
    assert figs["train_bf16_samples_per_s"]["note"] == "no bf16 hardware"


def test_cpu_variant_is_null_without_runs_and_only_validates_names(tmp_path, monkeypatch):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'empty.db'}")
    fig = run_all.cpu_variant_from_store(tmp_path)
    assert fig["value"] is None and "no finished cpu-preset run" in fig["note"]
    assert run_all.select_groups(["fps_ms_20k", "fps", "ads_ms_per_10k"]) == [
        "fps",
        "refine_metrics",
    ]
    with pytest.raises(ValueError, match="unknown benchmark"):
        run_all.select_groups(["nope"])
    with pytest.raises(SystemExit):
        run_all.main(["--only", "nope"])


@pytest.mark.slow
def test_baselines_bench_times_both_methods_beside_the_network():
    """The baselines' figures come with the network's time on the same segments, and the
    estimates they time are right (fpfh on half-visible asymmetric objects)."""
    from benchmarks import bench_baselines

    res = bench_baselines.run(quick=True)
    assert set(res) == {"baseline_fpfh_ms_per_object", "baseline_ppf_ms_per_object"}
    for fig in res.values():
        assert FIGURE_KEYS <= set(fig)
        assert fig["value"] > 0 and fig["reference"]["value"] > 0
        assert fig["ratio"] == pytest.approx(fig["value"] / fig["reference"]["value"])
        assert len(fig["detail"]["ms_all"]) == fig["detail"]["segments"] == 2
    # RANSAC runs on several threads, so its draws are not reproducible: a half-visible
    # asymmetric object at 1 mm noise is recovered anyway (8 deg in test_baselines)
    assert max(res["baseline_fpfh_ms_per_object"]["detail"]["rotation_error_deg_all"]) < 10


def _fig(value: float) -> dict:
    return {"value": value, "unit": "s", "what": f"w{value}", "reference": None}


def _report_to_merge_into(tmp_path, monkeypatch) -> dict:
    """A report of two figures in ``tmp_path`` (its JSON only) and an fps runner that gives
    ``fps_ms_20k``, the figure a merge then adds between them."""
    monkeypatch.setattr(run_all, "RUNNERS", {"fps": lambda *_: {"fps_ms_20k": _fig(2.0)}})
    first = run_all.run(["fps"], quick=True, out_dir=tmp_path)
    first["figures"] = {"infer_ms_per_object": _fig(1.0), "cpu_variant_wall_s": _fig(3.0)}
    (tmp_path / "benchmarks.json").write_text(json.dumps(first))
    return first


def _listed(lines: list[str]) -> tuple[list[str], list[str]]:
    """The figures of a report's table rows and of its description lines, in order."""
    rows = [line.split("`")[1] for line in lines if line.startswith("| `")]
    described = [line.split("`")[1] for line in lines if line.startswith("- `")]
    return rows, described


def test_merge_replaces_or_inserts_only_the_figures_run(tmp_path, monkeypatch):
    """--merge: the figures run now go into the existing report in report order, each row
    naming the machine (described once) and the date it was measured on; the other figures keep
    theirs."""

    first = _report_to_merge_into(tmp_path, monkeypatch)
    (tmp_path / "benchmarks.md").write_text(run_all.render_markdown(first))

    run_all.run(["fps"], quick=True, out_dir=tmp_path, merge=True)
    saved = json.loads((tmp_path / "benchmarks.json").read_text())
    assert list(saved["figures"]) == ["infer_ms_per_object", "fps_ms_20k", "cpu_variant_wall_s"]
    assert saved["figures"]["fps_ms_20k"]["measured"]["quick"] is True
    assert saved["started"] == first["started"]
    merged = (tmp_path / "benchmarks.md").read_text().splitlines()
    rows, described = _listed(merged)
    assert rows == described == ["infer_ms_per_object", "fps_ms_20k", "cpu_variant_wall_s"]
    # one machine here: described once, named by every row, with the date of each run
    machines = [line for line in merged if line.startswith("- M")]
    assert len(machines) == 1 and machines[0].startswith("- M1: ")
    for line in merged:
        if line.startswith("| `"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            assert cells[-2] == "M1" and cells[-1] == first["started"][:10]
    # merging again gives the same lines
    run_all.run(["fps"], quick=True, out_dir=tmp_path, merge=True)
    assert (tmp_path / "benchmarks.md").read_text().splitlines() == merged


def test_rows_of_other_machines_name_theirs(tmp_path, monkeypatch):
    """A figure merged from a run on another CPU names that CPU's own entry; a figure stored
    without its CPU says so instead of borrowing the report's."""
    first = _report_to_merge_into(tmp_path, monkeypatch)
    first["figures"]["infer_ms_per_object"]["measured"] = {
        "command": "x",
        "commit": "c",
        "started": "2026-01-02 03:04:05 UTC",
        "quick": False,
        "machine": "Another CPU (flags avx2); load average at start [1.0, 1.0, 1.0]",
    }
    first["figures"]["cpu_variant_wall_s"]["measured"] = {
        "command": "y",
        "commit": "d",
        "started": "2026-01-03 00:00:00 UTC",
        "quick": False,
    }
    lines = run_all.render_markdown(first).splitlines()
    machines = [line for line in lines if line.startswith("- M")]
    assert machines[0] == "- M1: Another CPU (flags avx2)"
    assert machines[1].startswith("- M2: not recorded")
    assert len(machines) == 2
    row = next(line for line in lines if line.startswith("| `infer_ms_per_object`"))
    assert row.rstrip(" |").endswith("M1 | 2026-01-02")
    described = next(line for line in lines if line.startswith("- `infer_ms_per_object`"))
    assert "[1.0, 1.0, 1.0]" in described


def test_merge_keeps_the_sections_written_after_the_table(tmp_path, monkeypatch):
    """Hand-written sections after the rendered part (its last line :data:`END`) stay as they
    are; the new figure joins the rendered table and list."""

    first = _report_to_merge_into(tmp_path, monkeypatch)
    older = [
        "",
        "## An older machine",
        "",
        "| figure | value | unit | reference | ratio | target | met |",
        "|---|---|---|---|---|---|---|",
        "| `infer_ms_per_object` | 9 | ms | - | - | - | - |",
        "",
        "- `infer_ms_per_object`: as it was then.",
        "",
    ]
    md = run_all.render_markdown(first) + "\n".join(older)
    (tmp_path / "benchmarks.md").write_text(md)

    run_all.run(["fps"], quick=True, out_dir=tmp_path, merge=True)
    merged = (tmp_path / "benchmarks.md").read_text()
    tail = "\n".join(older)
    assert merged.endswith(tail)
    rows, described = _listed(merged[: -len(tail)].splitlines())
    assert rows == described == ["infer_ms_per_object", "fps_ms_20k", "cpu_variant_wall_s"]


INTEL_CPUINFO = """processor\t: 0
vendor_id\t: GenuineIntel
model name\t: Intel(R) Xeon(R) Processor
flags\t\t: fpu sse avx avx2 fma avx512f avx512bw avx512_vnni avx512_bf16 amx_bf16 amx_tile
"""
AMD_CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
model name\t: AMD EPYC
flags\t\t: fpu sse avx avx2 fma
"""


def test_cpu_features_reads_the_gemm_flags_and_says_them():
    from cloudpose.runtime import cpu_features, describe_cpu

    intel = cpu_features(INTEL_CPUINFO)
    assert intel["vendor"] == "GenuineIntel" and intel["model"] == "Intel(R) Xeon(R) Processor"
    assert intel["bf16_hardware"] and intel["amx"]
    assert {"avx512f", "avx512_bf16", "amx_bf16", "amx_tile"} <= set(intel["flags"])
    assert "fpu" not in intel["flags"] and intel["cores"] >= 1
    amd = cpu_features(AMD_CPUINFO)
    assert not amd["bf16_hardware"] and not amd["amx"] and "avx512f" not in amd["flags"]
    assert "AMX bf16" in describe_cpu(intel) and "no bf16 GEMM" in describe_cpu(amd)
    assert "AMD EPYC" in describe_cpu(amd)
    # this machine's own view, as every benchmark header writes it
    here = cpu_features()
    assert here["torch_capability"] and here["usable_cores"] >= 1


def test_merged_figures_name_the_cpu_they_came_from(tmp_path, monkeypatch):
    fig = {"value": 2.0, "unit": "s", "what": "w", "reference": None}
    monkeypatch.setattr(run_all, "RUNNERS", {"fps": lambda *_: {"fps_ms_20k": dict(fig)}})
    run_all.run(["fps"], quick=True, out_dir=tmp_path)
    run_all.run(["fps"], quick=True, out_dir=tmp_path, merge=True)
    md = (tmp_path / "benchmarks.md").read_text()
    from cloudpose.runtime import cpu_features

    model = cpu_features()["model"]
    assert f"- M1: {model}" in md
    row = next(x for x in md.splitlines() if x.startswith("| `fps_ms_20k`"))
    assert "| M1 |" in row

"""The config dataclasses and the variant/preset registry (cloudpose/resources/registry/*.toml)."""

from __future__ import annotations

import dataclasses
import json
import textwrap

import pytest

import cloudpose.config as config
import cloudpose.registry as registry_module
from cloudpose.config import Config, DataConfig, ICPConfig, LossConfig, ModelConfig, TrainConfig
from cloudpose.registry import get_group, get_variant, groups, groups_of, presets, resolve, variants

SECTIONS = {
    "model": ModelConfig,
    "loss": LossConfig,
    "train": TrainConfig,
    "data": DataConfig,
    "icp": ICPConfig,
}


@pytest.fixture
def registry(tmp_path, monkeypatch):
    """Point the loader at temporary TOML files; returns a writer ``(variants, presets)``."""

    def write(variants_toml: str, presets_toml: str = "") -> None:
        (tmp_path / "variants.toml").write_text(textwrap.dedent(variants_toml))
        (tmp_path / "presets.toml").write_text(textwrap.dedent(presets_toml))
        registry_module._load_variants.cache_clear()
        registry_module._load_presets.cache_clear()

    monkeypatch.setattr(registry_module, "VARIANTS_FILE", tmp_path / "variants.toml")
    monkeypatch.setattr(registry_module, "PRESETS_FILE", tmp_path / "presets.toml")
    yield write
    registry_module._load_variants.cache_clear()
    registry_module._load_presets.cache_clear()


# --- resolve: base, then preset, then variant, then overrides ----------------------------------


def test_resolve_order_preset_variant_overrides(registry):
    registry(
        """
        [variant.wide]
        why = "wider"
        model.width = 2.0
        [variant.plain]
        why = "base"
        """,
        """
        [preset.p]
        why = "touches a model field too"
        model.width = 3.0
        model.rotation = "rot6d"
        train.epochs = 5
        """,
    )
    cfg = resolve("wide", "p")
    assert cfg.model.width == 2.0  # the variant beats the preset
    assert cfg.model.rotation == "rot6d"  # the preset beats the base
    assert cfg.train.epochs == 5
    assert cfg.train.batch_size == TrainConfig().batch_size  # untouched: base
    assert resolve("plain", "p").model.width == 3.0
    over = resolve("wide", "p", overrides={"model": {"width": 0.5}, "train": {"lr": 0.1}})
    assert over.model.width == 0.5  # overrides beat the variant
    assert over.model.rotation == "rot6d" and over.train.lr == 0.1 and over.train.epochs == 5


def test_resolve_real_registry():
    cfg = resolve("shared-all-2x", "smoke", seed=7, overrides={"train": {"epochs": 1}})
    assert (cfg.variant, cfg.preset, cfg.seed) == ("shared-all-2x", "smoke", 7)
    assert cfg.model.shared_layers == "all" and cfg.model.width == 2.0
    assert cfg.train.epochs == 1 and cfg.train.n_points == 64  # override, smoke preset
    assert cfg.model.rotation == "axis_angle" and cfg.loss == LossConfig(symmetric=True)
    assert resolve("l2").loss.rotation == "l2"
    assert resolve("quaternion").model.rotation == "quaternion"


def test_paper_literal_preset_is_the_papers_recipe():
    cfg = resolve("shared-0", "paper-literal")
    assert cfg.model == ModelConfig() and cfg.loss == LossConfig()  # raw xyz in metres
    assert cfg.train.bn_recalibrate == 0 and cfg.train.lr_schedule == "constant"
    assert (cfg.train.epochs, cfg.train.batch_size, cfg.train.lr, cfg.train.n_points) == (
        90,
        128,
        0.0008,
        256,
    )
    assert cfg.model.bn_momentum == 0.01  # the released code's BN decay 0.99
    assert cfg.model.point_mlp == (64, 64, 64, 128, 1024) and cfg.model.head == (512, 256)
    assert cfg.loss.alpha == 10.0 and cfg.loss.rotation == "geodesic"
    assert {"smoke", "cpu", "cpu-paper", "paper", "paper-literal"} <= set(presets())
    # paper = the same settings with the recipe findings; cpu-paper = cpu without them
    paper = resolve("shared-0", "paper")
    assert paper.train == dataclasses.replace(cfg.train, bn_recalibrate=50)
    assert (paper.model.xyz_scale, paper.model.rotation_input, paper.loss.symmetric) == (
        0.03,
        "centred",
        True,
    )
    cpu, cpu_paper = resolve("shared-0", "cpu"), resolve("shared-0", "cpu-paper")
    assert cpu.data == cpu_paper.data and cpu.train.epochs == cpu_paper.train.epochs
    assert cpu_paper.model == ModelConfig() and cpu_paper.loss == LossConfig()


# --- unknown names -----------------------------------------------------------------------------


def test_unknown_names_list_the_valid_ones():
    with pytest.raises(ValueError, match="unknown variant 'shared-9'") as e:
        resolve("shared-9")
    assert all(name in str(e.value) for name in variants())
    with pytest.raises(ValueError, match="unknown variant") as e:
        get_variant("nope")
    assert all(name in str(e.value) for name in variants())
    with pytest.raises(ValueError, match="unknown preset 'huge'") as e:
        resolve("shared-0", "huge")
    assert all(name in str(e.value) for name in presets())
    with pytest.raises(ValueError, match="unknown group 'widths'") as e:
        get_group("widths")
    assert all(name in str(e.value) for name in groups())


def test_unknown_fields_and_values_raise():
    with pytest.raises(ValueError, match=r"model\.depth"):
        resolve("shared-0", overrides={"model": {"depth": 3}})
    with pytest.raises(ValueError, match="optim"):
        resolve("shared-0", overrides={"optim": {"lr": 1.0}})
    with pytest.raises(ValueError, match="shared_layers"):
        ModelConfig(shared_layers=6)
    with pytest.raises(ValueError, match="rotation"):
        ModelConfig(rotation="euler")
    with pytest.raises(ValueError, match="width"):
        ModelConfig(width=0)
    with pytest.raises(ValueError, match=r"loss\.rotation"):
        LossConfig(rotation="l1")
    with pytest.raises(ValueError, match="shared_layers"):
        resolve("shared-0", overrides={"model": {"shared_layers": "some"}})


def test_loader_rejects_bad_registry(registry):
    registry("[variant.a]\nmodel.width = 2.0\n")
    with pytest.raises(ValueError, match="'a' has no 'why'"):
        variants()
    registry('[variant.a]\nwhy = "x"\n[group.g]\nmembers = ["a", "b"]\n')
    with pytest.raises(ValueError, match=r"unknown variants \['b'\]"):
        groups()
    registry('[variant.a]\nwhy = "x"\nmodel.widht = 2.0\n')
    with pytest.raises(ValueError, match=r"model\.widht"):
        variants()


# --- the registry's content --------------------------------------------------------------------


def test_every_variant_has_a_why_and_a_minimal_delta():
    # the base and the proposed system under every preset: what a variant can change
    bases = [Config()] + [resolve("shared-0", p) for p in presets()]
    assert variants()
    for name, v in variants().items():
        assert v.name == name and len(v.why) > 10
        for section, fields in v.delta.items():
            for key, value in fields.items():
                # a delta lists only what it changes, from the base or under some preset
                assert any(getattr(getattr(b, section), key) != value for b in bases), (
                    f"{name}: {section}.{key}"
                )
        resolve(name)  # every variant resolves to a valid config
    assert get_variant("shared-0").describe() == "(base)"
    assert get_variant("l2").describe() == "loss.rotation=l2"


def test_groups_as_the_issue_lists_them():
    g = groups()
    for group in g.values():
        assert all(m in variants() for m in group.members)
        assert set(group.labels) <= set(group.members)
    shared = g["shared"].members
    assert shared[:7] == (
        "shared-0",
        "shared-1",
        "shared-2",
        "shared-3",
        "shared-4",
        "shared-5",
        "shared-all",
    )
    assert "shared-all-2x" in shared and len(shared) == 9
    assert g["rotation"].members == ("shared-0", "quaternion", "rot6d")
    assert g["loss"].members == ("shared-0", "l2")
    assert groups_of("shared-0") == ["shared", "rotation", "loss", "symmetry", "centre"]
    assert g["symmetry"].members == ("shared-0", "geodesic-plain")
    assert g["centre"].members == (
        "shared-0",
        "centre-median",
        "centre-trimmed",
        "centre-trimmed-translation",
    )
    assert groups_of("rot6d") == ["rotation"]
    # every variant belongs to some group
    assert all(groups_of(name) for name in variants())


def test_variants_match_design_table():
    for k in range(6):
        assert resolve(f"shared-{k}").model.shared_layers == k
    assert resolve("shared-all").model.shared_layers == "all"
    assert resolve("shared-all").model.width == 1.0
    assert resolve("rot6d").model.rotation == "rot6d"


# --- serialisation -----------------------------------------------------------------------------


def test_config_fingerprint():
    a = resolve("shared-3", "cpu", seed=2)
    assert a.fingerprint() == resolve("shared-3", "cpu", seed=2).fingerprint()
    assert len(a.fingerprint()) == 16
    # through JSON (as stored in checkpoints and MLflow) it is the same config
    assert Config.from_dict(json.loads(json.dumps(a.to_dict()))).fingerprint() == a.fingerprint()
    others = [
        resolve("shared-3", "cpu", seed=3),
        resolve("shared-4", "cpu", seed=2),
        resolve("shared-3", "cpu-paper", seed=2),
        resolve("shared-3", "cpu", seed=2, overrides={"train": {"lr": 1e-3}}),
        dataclasses.replace(a, data=dataclasses.replace(a.data, test_frames=151)),
    ]
    assert len({a.fingerprint(), *(o.fingerprint() for o in others)}) == 1 + len(others)


def test_rotation_centre_at_its_implied_value_keeps_a_stored_runs_identity():
    cfg = resolve("centre-trimmed", "cpu-online", seed=1)
    assert cfg.model.rotation_centre == "centre"
    stored = cfg.to_dict()
    del stored["model"]["rotation_centre"]  # a run stored before the field existed
    assert Config.from_dict(stored) == cfg
    assert Config.from_dict(stored).fingerprint() == cfg.fingerprint()
    translation_only = resolve("centre-trimmed-translation", "cpu-online", seed=1)
    assert translation_only.fingerprint() != cfg.fingerprint()
    assert dataclasses.replace(translation_only.model, rotation_centre="centre") == cfg.model


def test_cpu_is_cpu_paper_with_the_recipe():
    # the cpu preset extends cpu-paper: the same frames and segment cache, the recipe on top
    cpu, literal = resolve("shared-0", "cpu", seed=1), resolve("shared-0", "cpu-paper", seed=1)
    assert cpu.data == literal.data and (cpu.train.epochs, cpu.train.batch_size) == (25, 32)
    assert dataclasses.replace(literal.train, bn_recalibrate=50, lr_schedule="cosine") == cpu.train


# --- presets that extend a preset --------------------------------------------------------------

# Config fingerprints (MLflow tag ``config``, run folder suffix) of every registered preset: the
# committed stores' runs are found by them, so a change to presets.toml must leave them as they
# are (a new preset adds its own here).
PRESET_FINGERPRINTS = {
    "smoke": ("05f1b3f3ce5bf427", "dadbbb7efc3c35d2"),
    "cpu": ("ef338e3a7c1144f5", "fd247e1025f0f450"),
    "online": ("b7a924ca3b84b65e", "66b2722a2266fa5b"),
    "cpu-online": ("541c58429a09604b", "aa68bfa81e905d74"),
    "cpu-online-4x": ("1a9737c49051fa74", "3381f449b8c5b563"),
    "cpu-online-4x-2t": ("ec6711806bd723a1", "f34c064faaca6326"),
    "gpu": ("f21fd55a7d85d916", "b3230d247b40347d"),
    "cpu-paper": ("44912df2a29512f6", "acec99161b886f06"),
    "paper": ("fd061ca528aaa89b", "dc8ea5e7633f61b4"),
    "paper-literal": ("16fad932f400e5c0", "26c7759ed429f54f"),
}

# The presets that now extend another, spelled out field by field as presets.toml held them
# before ``extends`` (commit c90e01f).
SPELLED_OUT = """
[preset.cpu]
why = "cpu"
data.train_frames = 800
data.test_frames = 150
data.synth_version = 1
data.segment_streams = "frame"
train.epochs = 25
train.batch_size = 32
model.xyz_scale = 0.03
model.rotation_input = "centred"
loss.symmetric = true
train.lr_schedule = "cosine"

[preset.cpu-online]
why = "cpu-online"
data.train_source = "online"
data.train_frames = 100
data.test_frames = 420
data.synth_version = 2
data.online_epoch_segments = 8192
data.online_reuse = 4
data.online_workers = 1
train.epochs = 16
train.batch_size = 32
train.augment_roll_deg = 15.0
train.augment_depth_noise_mm = 3.0
model.xyz_scale = 0.03
model.rotation_input = "centred"
loss.symmetric = true
loss.symmetry_table = 2
train.lr_schedule = "cosine"

[preset.cpu-online-4x]
why = "cpu-online-4x"
data.train_source = "online"
data.train_frames = 100
data.test_frames = 420
data.synth_version = 2
data.online_epoch_segments = 8192
data.online_reuse = 2
data.online_version = 3
data.online_workers = 1
train.epochs = 64
train.batch_size = 32
train.augment_roll_deg = 15.0
train.augment_depth_noise_mm = 3.0
model.xyz_scale = 0.03
model.rotation_input = "centred"
loss.symmetric = true
loss.symmetry_table = 2
train.lr_schedule = "cosine"

[preset.gpu]
why = "gpu"
data.train_source = "online"
data.train_frames = 100
data.test_frames = 420
data.synth_version = 2
data.online_epoch_segments = 32768
data.online_reuse = 1
data.online_version = 3
data.online_workers = 15
train.epochs = 32
train.batch_size = 32
train.augment_roll_deg = 15.0
train.augment_depth_noise_mm = 3.0
model.xyz_scale = 0.03
model.rotation_input = "centred"
loss.symmetric = true
loss.symmetry_table = 2
train.lr_schedule = "cosine"
"""


def test_every_preset_keeps_the_fingerprint_its_stored_runs_have():
    assert set(presets()) == set(PRESET_FINGERPRINTS)
    for name, (shared0, shared_all) in PRESET_FINGERPRINTS.items():
        assert resolve("shared-0", name, seed=1).fingerprint() == shared0, name
        assert resolve("shared-all", name, seed=2).fingerprint() == shared_all, name


def test_presets_that_extend_resolve_as_their_spelled_out_fields(tmp_path, monkeypatch):
    spelled = registry_module.read_presets(_write(tmp_path / "spelled.toml", SPELLED_OUT))
    assert set(spelled) <= set(presets())
    for name in spelled:
        with monkeypatch.context() as m:
            m.setattr(registry_module, "PRESETS_FILE", tmp_path / "spelled.toml")
            registry_module._load_presets.cache_clear()
            plain = {v: resolve(v, name, seed=3) for v in variants()}
        registry_module._load_presets.cache_clear()
        for v, cfg in plain.items():
            assert resolve(v, name, seed=3) == cfg, (v, name)
            assert resolve(v, name, seed=3).fingerprint() == cfg.fingerprint(), (v, name)


def _write(path, text):
    path.write_text(textwrap.dedent(text))
    return path


def test_a_preset_extends_a_chain_of_bases_its_own_fields_winning(registry):
    registry(
        """
        [variant.plain]
        why = "base"
        """,
        """
        [preset.leaf]
        why = "the leaf"
        extends = "mid"
        train.epochs = 3
        [preset.mid]
        why = "the middle"
        extends = "root"
        train.batch_size = 8
        data.test_frames = 7
        [preset.root]
        why = "the root"
        train.epochs = 50
        train.batch_size = 64
        model.width = 2.0
        """,
    )
    leaf = resolve("plain", "leaf")
    assert (leaf.train.epochs, leaf.train.batch_size, leaf.model.width) == (3, 8, 2.0)
    assert leaf.data.test_frames == 7 and leaf.preset == "leaf"
    assert resolve("plain", "mid").train.epochs == 50
    assert presets() == {"leaf": "the leaf", "mid": "the middle", "root": "the root"}


@pytest.mark.parametrize(
    "presets_toml, message",
    [
        (
            '[preset.a]\nwhy = "a"\nextends = "nope"\n',
            r"\[a\]: extends = 'nope', which is no preset; valid presets: a",
        ),
        (
            '[preset.a]\nwhy = "a"\nextends = "b"\n[preset.b]\nwhy = "b"\nextends = "a"\n',
            r"\[b\]: extends = 'a' makes a cycle: a -> b -> a",
        ),
        ('[preset.a]\nwhy = "a"\nextends = "a"\n', r"\[a\]: extends = 'a' makes a cycle: a -> a"),
        ('[preset.a]\nwhy = "a"\nextends = 3\n', r"\[a\]: extends = 3: expected a preset's name"),
        (
            '[preset.a]\nwhy = "a"\nextends = "b"\n[preset.b]\nwhy = "b"\ntrain.epoch = 2\n',
            r"\[b\]: unknown field train.epoch",
        ),
    ],
)
def test_extends_names_the_preset_and_field_it_cannot_resolve(tmp_path, presets_toml, message):
    path = _write(tmp_path / "presets.toml", presets_toml)
    with pytest.raises(ValueError, match=message):
        registry_module.read_presets(path)


@pytest.mark.parametrize("preset", list(presets()))
def test_config_round_trip(preset):
    for name in variants():
        cfg = resolve(name, preset, seed=3)
        assert Config.from_dict(cfg.to_dict()) == cfg
        # through JSON too (tuples become lists), as a checkpoint or MLflow stores it
        assert Config.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg


def test_from_dict_rejects_unknown_keys():
    d = Config().to_dict()
    d["optimizer"] = {}
    with pytest.raises(ValueError, match="optimizer"):
        Config.from_dict(d)


def test_from_dict_rejects_unknown_nested_keys():
    d = Config().to_dict()
    d["model"]["depth"] = 3
    with pytest.raises(ValueError, match="depth"):
        Config.from_dict(d)


def test_flat_keys():
    cfg = resolve("shared-3", "cpu", seed=2)
    flat = cfg.flat()
    expected = {"variant", "preset", "seed"} | {
        f"{s}.{f.name}" for s, cls in SECTIONS.items() for f in dataclasses.fields(cls)
    }
    assert set(flat) == expected
    assert flat["model.shared_layers"] == 3 and flat["seed"] == 2 and flat["variant"] == "shared-3"
    assert flat["train.batch_size"] == cfg.train.batch_size
    assert not any(isinstance(v, dict) for v in flat.values())
    # MLflow keys allow letters, digits and _ - . / space only
    assert all(set(k) <= set("abcdefghijklmnopqrstuvwxyz0123456789_-./ ") for k in flat)


def test_new_training_fields_are_checked():
    with pytest.raises(ValueError, match="epochs"):
        config.TrainConfig(epochs=0)
    with pytest.raises(ValueError, match="sampler"):
        config.TrainConfig(sampler="nope")
    with pytest.raises(ValueError, match="lr_schedule"):
        config.TrainConfig(lr_schedule="step")
    with pytest.raises(ValueError, match="rotation_input"):
        config.ModelConfig(rotation_input="world")
    with pytest.raises(ValueError, match="xyz_scale"):
        config.ModelConfig(xyz_scale=0.0)
    with pytest.raises(ValueError, match="rotation_centre"):
        config.ModelConfig(rotation_centre="median")
    # the mean-centred rotation input needs a rotation branch of its own on centred points
    with pytest.raises(ValueError, match="rotation_input"):
        config.ModelConfig(rotation_centre="mean", rotation_input="raw")
    with pytest.raises(ValueError, match="shared_layers"):
        config.ModelConfig(rotation_centre="mean", rotation_input="centred", shared_layers=2)
    assert config.DataConfig(classes=["011_banana"]).classes == ("011_banana",)


def test_cli_set_parses_toml_values():
    from cloudpose.registry import parse_overrides

    got = parse_overrides(
        [
            "train.epochs=3",
            "model.rotation_input=centred",
            "loss.symmetric=true",
            "data.classes=['011_banana', '025_mug']",
            "model.xyz_scale=0.1",
        ]
    )
    assert got == {
        "train": {"epochs": 3},
        "model": {"rotation_input": "centred", "xyz_scale": 0.1},
        "loss": {"symmetric": True},
        "data": {"classes": ["011_banana", "025_mug"]},
    }
    cfg = resolve("shared-0", "smoke", 1, got)
    assert cfg.data.classes == ("011_banana", "025_mug") and cfg.train.epochs == 3
    with pytest.raises(ValueError, match=r"section\.field=value"):
        parse_overrides(["epochs=3"])


def test_override_values_must_have_their_fields_type():
    for bad in ({"epochs": "two"}, {"epochs": 2.5}, {"epochs": True}, {"lr": "fast"}):
        ((key, value),) = bad.items()
        with pytest.raises(ValueError, match=rf"train\.{key}={value!r}: expected"):
            resolve("shared-0", "smoke", 1, {"train": bad})
    with pytest.raises(ValueError, match=r"data\.classes='011_banana': expected tuple"):
        resolve("shared-0", "smoke", 1, {"data": {"classes": "011_banana"}})
    # what the fields take: an integer for a float, a string or integer for shared_layers
    assert resolve("shared-0", "smoke", 1, {"train": {"lr": 1}}).train.lr == 1
    cfg = resolve("shared-0", "smoke", 1, {"model": {"shared_layers": "all"}})
    assert cfg.model.shared_layers == "all"


@pytest.mark.parametrize(
    ("train", "message"),
    [
        ({"n_points": 0}, "train.n_points must be >= 1"),
        ({"lr": -1}, "train.lr must be > 0"),
        ({"lr": 0.0}, "train.lr must be > 0"),
        ({"lr": float("nan")}, "train.lr must be > 0"),
        ({"val_fraction": 1.0}, r"train.val_fraction must be in \[0, 1\)"),
        ({"n_points": 2048}, "exceeds data.n_fps=1024"),
    ],
)
def test_training_values_out_of_range_fail_at_resolve(train, message):
    with pytest.raises(ValueError, match=message):
        resolve("shared-0", "smoke", 1, {"train": train})

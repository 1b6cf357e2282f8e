"""The random streams of training (cloudpose.train.seeds) and the identity of the runs they
made: every preset keeps the seed arithmetic its stored runs trained with."""

from __future__ import annotations

import itertools

import pytest
import torch

from cloudpose.config import Config
from cloudpose.registry import presets, resolve
from cloudpose.train.seeds import PURPOSES, generator, seed_for

# Config fingerprints (MLflow tag ``config``, run folder suffix) of registered configs as they
# were before ``train.seed_streams`` existed, computed from the commit before it.
FINGERPRINTS = {
    ("shared-0", "cpu", 1): "ef338e3a7c1144f5",
    ("shared-0", "cpu-online", 1): "541c58429a09604b",
    ("shared-0", "cpu-paper", 1): "44912df2a29512f6",
    ("shared-0", "online", 1): "b7a924ca3b84b65e",
    ("shared-0", "paper", 1): "fd061ca528aaa89b",
    ("shared-0", "paper-literal", 1): "16fad932f400e5c0",
    ("shared-0", "smoke", 1): "05f1b3f3ce5bf427",
    ("shared-all", "cpu-online", 2): "aa68bfa81e905d74",
    ("l2", "cpu", 1): "be07f52080993624",
    ("quaternion", "cpu-paper", 2): "3c2255d966980c5a",
    ("shared-3", "online", 1): "cf47f41a84cf631c",
}


def _indices(purpose: str, epochs: int, batches: int):
    ranges = {"epoch": range(epochs), "batch": range(batches)}
    return itertools.product(*(ranges[name] for name in PURPOSES[purpose]))


def test_no_two_purposes_share_a_stream():
    """Every (seed, purpose, index) of a run's first epochs has a seed of its own; under the
    seed arithmetic, the batch order of epoch e is the roll stream of epoch 0, batch e."""
    seen: dict[int, tuple] = {}
    for seed, purpose in itertools.product(range(4), PURPOSES):
        for index in _indices(purpose, epochs=12, batches=40):
            s = seed_for(seed, purpose, *index)
            assert 0 <= s < 2**63
            assert s not in seen, f"{(seed, purpose, *index)} shares a stream with {seen[s]}"
            seen[s] = (seed, purpose, *index)
    assert len(seen) == 4 * (2 + 2 * 12 + 2 * 12 * 40)
    # the overlap the purpose streams remove, and its draws
    for e in range(12):
        assert seed_for(3, "order", e, streams="arithmetic") == seed_for(
            3, "roll", 0, e, streams="arithmetic"
        )
        order, roll = generator(3, "order", e), generator(3, "roll", 0, e)
        assert not torch.equal(torch.rand(8, generator=order), torch.rand(8, generator=roll))


def test_a_stream_depends_on_its_arguments_alone():
    a = torch.rand(4, generator=generator(5, "depth_noise", 2, 7))
    assert torch.equal(a, torch.rand(4, generator=generator(5, "depth_noise", 2, 7)))
    assert seed_for(5, "init") != seed_for(6, "init")


def test_the_seed_arithmetic_is_the_stored_runs():
    """``arithmetic``: the seeds every run stored before ``train.seed_streams`` drew from."""
    s, e, b = 3, 5, 11
    index = {"epoch": e, "batch": b}
    got = {
        p: seed_for(s, p, *(index[n] for n in names), streams="arithmetic")
        for p, names in PURPOSES.items()
    }
    assert got == {
        "init": s,
        "probe": 0,
        "order": s * 1_000_003 + e,
        "roll": s * 1_000_003 + e * 100_003 + b,
        "depth_noise": s * 7_000_003 + e * 100_003 + b,
        "bn_recalibrate": s + e,
    }


def test_a_stream_is_named_and_indexed_as_its_purpose_says():
    with pytest.raises(ValueError, match=r"'order' takes .*'epoch'"):
        seed_for(1, "order", 0, 1)
    with pytest.raises(ValueError, match=r"expected one of .*'roll'"):
        seed_for(1, "rolls", 0, 1)
    with pytest.raises(ValueError, match="seed_streams"):
        seed_for(1, "init", streams="hash")


@pytest.mark.parametrize(("variant", "preset", "seed"), sorted(FINGERPRINTS))
def test_registered_configs_keep_their_fingerprints(variant, preset, seed):
    cfg = resolve(variant, preset, seed)
    assert cfg.train.seed_streams == "arithmetic"
    assert cfg.fingerprint() == FINGERPRINTS[variant, preset, seed]


def test_every_preset_keeps_the_stored_runs_streams():
    """A config stored without the field is the arithmetic one, with its fingerprint; the
    purpose streams are another config."""
    for name in presets():
        cfg = resolve("shared-0", name, 1)
        stored = cfg.to_dict()
        del stored["train"]["seed_streams"]
        assert Config.from_dict(stored) == cfg and cfg.train.seed_streams == "arithmetic"
        assert Config.from_dict(stored).fingerprint() == cfg.fingerprint()
        other = resolve("shared-0", name, 1, {"train": {"seed_streams": "purpose"}})
        assert other.fingerprint() != cfg.fingerprint()
    with pytest.raises(ValueError, match="seed_streams"):
        resolve("shared-0", "smoke", 1, {"train": {"seed_streams": "hash"}})

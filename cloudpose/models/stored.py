"""A network checkpoint in fewer bytes: the stored forms of its float32 weights.

- :data:`FLOAT16`: every float32 tensor of the network's state as float16;
- :data:`FLOAT24`: every float32 tensor rounded to its three high bytes (sign, exponent and 15
  of the 23 mantissa bits, to nearest), stored as three byte planes (uint8, ``(3, *shape)``:
  the plane of the sign and exponent compresses well).

State dict keys, integer buffers, float tensors of other dtypes and every other entry of the
checkpoint (its config) are kept; the packed checkpoint names its form and the tensors it
changed (:data:`FORM_KEY`). :func:`decode` gives back a float32 checkpoint with the original's
keys and dtypes, the values as rounded: :func:`cloudpose.infer.load_checkpoint` reads every
form so. Which form a checkpoint may take (its poses must not move) is the archive's rule
(:mod:`cloudpose.archive.checkpoints`); the shipped network and a compact store use it.
"""

from __future__ import annotations

import io
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

FLOAT16 = "float16"
FLOAT24 = "float24"
FLOAT32 = "float32"

REDUCED = {FLOAT16: ".fp16.pt", FLOAT24: ".f24.pt"}
"""Form -> the ending of a packed checkpoint's name (``model.pt`` -> ``model.fp16.pt``), in
the order they are tried (fewest bytes first)."""

FORM_KEY = "cloudpose_stored_as"
"""Entry of a packed checkpoint: ``{"form": FORM, "keys": [state keys changed]}``."""


def _float24(t: torch.Tensor) -> torch.Tensor:
    """A float32 tensor's three high bytes, rounded to nearest: uint8 ``(3, *shape)``."""
    u = t.detach().contiguous().cpu().numpy().view(np.uint32).astype(np.uint64)
    finite = np.isfinite(t.detach().cpu().numpy())
    top = np.where(finite, (u + 0x80) >> 8, u >> 8)  # a carry into the exponent is right
    planes = np.stack([(top >> 16) & 0xFF, (top >> 8) & 0xFF, top & 0xFF]).astype(np.uint8)
    return torch.from_numpy(np.ascontiguousarray(planes))


def _from_float24(planes: torch.Tensor) -> torch.Tensor:
    """The float32 tensor of :func:`_float24`'s byte planes."""
    p = planes.numpy().astype(np.uint32)
    u = (p[0] << 24) | (p[1] << 16) | (p[2] << 8)
    return torch.from_numpy(np.ascontiguousarray(u.view(np.float32)))


def encode(ckpt: Mapping[str, Any], form: str) -> dict[str, Any]:
    """The packed checkpoint of ``ckpt`` (keys ``model``, ``config``, ...) in ``form``: each
    float32 tensor of its ``model`` state in float16 or as float24 byte planes, the rest as it
    is, and :data:`FORM_KEY` naming the tensors changed."""
    if form not in REDUCED:
        raise ValueError(f"unknown checkpoint form {form!r}; expected one of {list(REDUCED)}")
    model, changed = {}, []
    for key, value in ckpt["model"].items():
        if isinstance(value, torch.Tensor) and value.dtype == torch.float32:
            model[key] = value.half() if form == FLOAT16 else _float24(value)
            changed.append(key)
        else:
            model[key] = value
    out = {k: (model if k == "model" else v) for k, v in ckpt.items()}
    out[FORM_KEY] = {"form": form, "keys": changed}
    return out


def decode(packed: Mapping[str, Any]) -> dict[str, Any]:
    """The float32 checkpoint of a packed one (:func:`encode`): the same keys and dtypes as
    the original, the values as the form rounded them."""
    meta = packed[FORM_KEY]
    form, changed = meta["form"], set(meta["keys"])
    if form not in REDUCED:
        raise ValueError(f"unknown checkpoint form {form!r}; expected one of {list(REDUCED)}")
    absent = sorted(changed - set(packed["model"]))
    if absent:
        raise ValueError(f"{FORM_KEY} names state tensors that it lacks: {absent[:3]}")
    model = {}
    for key, value in packed["model"].items():
        if key in changed:
            _check_stored(key, value, form)
            value = value.float() if form == FLOAT16 else _from_float24(value)
        model[key] = value
    return {k: (model if k == "model" else v) for k, v in packed.items() if k != FORM_KEY}


def _check_stored(key: str, value: Any, form: str) -> None:
    """``ValueError`` unless ``value`` is a tensor as :func:`encode` stores one in ``form``:
    float16, or float24's uint8 byte planes ``(3, *shape)``."""
    if form == FLOAT16:
        ok = isinstance(value, torch.Tensor) and value.dtype == torch.float16
        expected = "a float16 tensor"
    else:
        ok = (
            isinstance(value, torch.Tensor)
            and value.dtype == torch.uint8
            and value.dim() >= 1
            and value.shape[0] == 3
        )
        expected = "uint8 byte planes (3, *shape)"
    if not ok:
        got = (
            f"{value.dtype} {tuple(value.shape)}"
            if isinstance(value, torch.Tensor)
            else type(value).__name__
        )
        raise ValueError(f"state tensor {key!r} is {got}, not {form}'s {expected}")


def round_trip(ckpt: Mapping[str, Any], form: str) -> dict[str, Any]:
    """``ckpt`` as unpacking its ``form`` gives it back (float32, rounded)."""
    return decode(encode(ckpt, form))


def to_bytes(obj: Mapping[str, Any]) -> bytes:
    """``torch.save`` of ``obj`` as bytes (the same bytes for the same values, whatever the
    file's name: torch names the archive's root after a file, ``archive`` in memory)."""
    buf = io.BytesIO()
    torch.save(dict(obj), buf)
    return buf.getvalue()

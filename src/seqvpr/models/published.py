"""Published checkpoints of the reference codes, converted into seqvpr model folders, strictly.

Containers: a raw ``state_dict``; SeqNet/SeqMatchNet training checkpoints (``{"epoch", "state_dict", "recalls",
"best_score", ...}``, whose numpy float64 scalars load through an allow-list, never through unrestricted
unpickling); CosPlace/JIST training checkpoints (``model_state_dict``). Prefixes ``module.`` (DataParallel) and
``pool.module.`` (SeqMatchNet on several GPUs) are removed. Kinds: SeqNet (``pool.0.conv.*``, any w) and
SeqMatchNet (``pool.1.conv.*``, kernel 1 = the per-frame transform ``normalize(W x + B)``, with upstream's forward:
no input normalisation); CosPlace (``*_cosplace.pth``: ``backbone.0/1/4..7.*``, ``aggregation.1.p``,
``aggregation.3.*``; ResNet-18 or -50 by the head's input size) becomes a frame encoder folder, images at 512 x 384;
JIST (``JIST_r18_512_seqgem.pth``, ``best_model.pth``: the CosPlace keys under ``model.`` plus ``seq_gem.p``) a JIST
folder with upstream's forward: SeqGeM without final normalisation (searched by exact L2), images at 480 x 640.
A missing or unexpected key, or a wrong shape, is a one-line error naming it as in the file; the folder records
the source file and its sha256.

Same name as ``seqvpr.cli.published``: published checkpoints read into models; the import command there.
"""

from __future__ import annotations

import json
import pickle
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from seqvpr.errors import SeqvprError
from seqvpr.identity import digest_file
from seqvpr.io import check_output_apart

PREFIXES = (("module.", ""), ("pool.module.", "pool."))
KINDS_KEYS = {
    "seqnet": ("pool.0.conv.weight", "pool.0.conv.bias"),
    "seqmatchnet": ("pool.1.conv.weight", "pool.1.conv.bias"),
}
JIST_POOL, JIST_PREFIX = "seq_gem.p", "model."
#: JIST's test-time input: 480 x 640 (H x W) with ImageNet normalisation
JIST_IMAGE_SIZE = (640, 480)


@dataclass(frozen=True)
class ImportedModel:
    """What ``import_checkpoint`` wrote: the kind, the model folder, and the source file's sha256."""

    kind: str
    folder: Path
    sha256: str


def numpy_scalar_globals() -> list:
    """The numpy globals a pickled float64 scalar needs (numpy 1 and 2 names): all the allow-list admits."""
    allowed: list = [np.dtype, type(np.dtype(np.float64)), type(np.dtype(np.int64))]
    for name in ("numpy._core.multiarray", "numpy.core.multiarray"):
        try:
            module = __import__(name, fromlist=["scalar"])
        except ImportError:
            continue
        allowed.append((module.scalar, f"{name}.scalar"))
    return allowed


def read_container(path: str | Path) -> dict[str, Any]:
    """The checkpoint's top-level object, loaded with ``weights_only`` and the numpy-scalar allow-list."""
    from seqvpr.arrays import check_regular_file

    path = Path(path)
    if not path.exists():
        raise SeqvprError(f"{path}: no such checkpoint file")
    check_regular_file(path, "a checkpoint file")
    try:
        with torch.serialization.safe_globals(numpy_scalar_globals()):
            content = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, OSError, ValueError, struct.error, IndexError) as error:
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        if first.startswith("Weights only load failed"):  # torch's advice to unpickle anything is not ours to give
            first = "not a torch file, or it holds objects beyond tensors and numpy scalars"
        raise SeqvprError(f"{path}: not a loadable checkpoint ({first[:200]})") from None
    if not isinstance(content, dict):
        raise SeqvprError(f"{path}: holds a {type(content).__name__}, not a state dict or checkpoint")
    return content


def state_dict_of(content: dict[str, Any], path: Path) -> dict[str, torch.Tensor]:
    """The weights of a container (raw state dict, ``state_dict`` or ``model_state_dict``), prefixes removed."""
    for key in ("state_dict", "model_state_dict"):
        if isinstance(content.get(key), dict):
            content = content[key]
            break
    state = {k: v for k, v in content.items() if torch.is_tensor(v)}
    if not state:
        raise SeqvprError(f"{path}: no tensors found (expected a state dict, or one under 'state_dict')")
    for prefix, replacement in PREFIXES:
        if all(k.startswith(prefix) for k in state):
            state = {replacement + k[len(prefix):]: v for k, v in state.items()}
    return state


def detect_kind(state: dict[str, torch.Tensor], path: Path) -> str:
    """The published model a state dict is, by its keys (SeqNet and SeqMatchNet checked strictly here; JIST and
    CosPlace by ``cosplace_state``), or a one-line error naming a key."""
    if JIST_POOL in state or any(k.startswith(JIST_PREFIX) for k in state):
        return "jist"
    for kind, keys in KINDS_KEYS.items():
        if keys[0] in state:
            unexpected = sorted(set(state) - set(keys))
            missing = [k for k in keys if k not in state]
            if unexpected or missing:
                which = f"unexpected key {unexpected[0]!r}" if unexpected else f"missing key {missing[0]!r}"
                raise SeqvprError(f"{path}: a {kind} checkpoint with an {which}")
            return kind
    if any(k.startswith(("backbone.", "aggregation.")) for k in state):
        return "cosplace"
    raise SeqvprError(f"{path}: not a SeqNet, SeqMatchNet, CosPlace or JIST checkpoint (no key "
                      f"{' or '.join(k[0] for k in KINDS_KEYS.values())!r}, 'aggregation.3.weight' or {JIST_POOL!r})")


def read_flags(path: str | Path | None) -> dict[str, Any]:
    """The run's ``flags.json`` (seqL, w, outDims...), or nothing."""
    if path is None:
        return {}
    if Path(path).exists():
        from seqvpr.arrays import check_regular_file

        check_regular_file(path, "a flags.json")
    try:
        flags = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise SeqvprError(f"{path}: no such flags file") from None
    except json.JSONDecodeError as error:
        raise SeqvprError(f"{path}: not valid JSON ({error.msg}, line {error.lineno})") from None
    if not isinstance(flags, dict):
        raise SeqvprError(f"{path}: expected a JSON object of flags")
    return flags


def conv_shapes(state: dict[str, torch.Tensor], prefix: str, path: Path) -> tuple[int, int, int]:
    """(out, in, w) of a Conv1d's weight, after checking the weight is 3-D and the bias [out]."""
    weight, bias = state[f"{prefix}.weight"], state[f"{prefix}.bias"]
    if weight.ndim != 3 or bias.shape != (weight.shape[0],):
        raise SeqvprError(f"{path}: {prefix}.weight {tuple(weight.shape)} and {prefix}.bias {tuple(bias.shape)} "
                          f"are not a Conv1d's [out, in, w] and [out]")
    return int(weight.shape[0]), int(weight.shape[1]), int(weight.shape[2])


def check_flag(flags: dict[str, Any], name: str, value: int, path: Path, flags_path: str | Path | None) -> None:
    """A flag that the weights fix must agree with them."""
    if name in flags and flags[name] is not None and int(flags[name]) != value:
        raise SeqvprError(f"{flags_path}: {name} = {flags[name]} but {path} holds {value}")


def file_sha256(path: Path) -> str:
    """The file's sha256 as plain hex (``seqvpr.identity.digest_file`` without its prefix)."""
    return digest_file(path).split(":", 1)[1]


def import_checkpoint(path: str | Path, out: str | Path, flags_path: str | Path | None = None) -> ImportedModel:
    """Convert a published SeqNet, SeqMatchNet, CosPlace or JIST checkpoint into a seqvpr model folder ``out``."""
    from seqvpr.models.configs import TransformConfig
    from seqvpr.models.seqmatchnet import FrameTransform, save_seqmatchnet
    from seqvpr.models.seqnet import save_seqnet
    from seqvpr.sequences.descriptors import SeqNet

    path = Path(path)
    check_output_apart(out, [path, flags_path], "the model folder")
    state = state_dict_of(read_container(path), path)
    kind, flags = detect_kind(state, path), read_flags(flags_path)
    sha = file_sha256(path)
    source = {"source": {"file": str(path), "sha256": sha, "flags": flags or None}}
    if kind == "jist":
        save_published_jist(state, out, int(flags.get("seq_length") or 5), source, path)
        return ImportedModel(kind, Path(out), sha)
    if kind == "cosplace":
        save_published_cosplace(state, out, source, path)
        return ImportedModel(kind, Path(out), sha)
    prefix = KINDS_KEYS[kind][0].rsplit(".", 1)[0]
    out_dim, in_dim, w = conv_shapes(state, prefix, path)
    check_flag(flags, "outDims", out_dim, path, flags_path)
    if kind == "seqnet":
        check_flag(flags, "w", w, path, flags_path)
        model = SeqNet(in_dim, out_dim, w)
        model.conv.load_state_dict({"weight": state[f"{prefix}.weight"], "bias": state[f"{prefix}.bias"]})
        length = int(flags.get("seqL") or w)
        save_seqnet(out, model, {"sequence": {"length": length}, **source})
    else:
        if w != 1:
            raise SeqvprError(f"{path}: {prefix}.weight has kernel width {w}; SeqMatchNet's transform has width 1")
        model = FrameTransform(TransformConfig(in_dim, out_dim, normalize_input=False))
        model.layers[0].load_state_dict({"weight": state[f"{prefix}.weight"][:, :, 0], "bias": state[f"{prefix}.bias"]})
        length = int(flags.get("seqL") or 1)
        save_seqmatchnet(out, model, {"sequence": {"length": length}, **source})
    return ImportedModel(kind, Path(out), sha)


def cosplace_state(
    state: dict[str, torch.Tensor], model: torch.nn.Module, path: Path, title: str = "CosPlace", *,
    prefix: str = "", target: str = "", extra: dict[str, str] | None = None,
) -> dict[str, torch.Tensor]:
    """A published state dict in ``model``'s names, strictly: the CosPlace keys (under ``prefix``: JIST's
    ``model.``) go to the frame encoder (under ``target``: JIST's ``encoder.``), ``extra`` maps further file keys
    (JIST's ``seq_gem.p``). Every file key needs a place of its shape and every model parameter a file key; the
    first that does not is a one-line error naming the key as in the file."""
    from seqvpr.models.cosplace import INPUT_BUFFERS, seqvpr_name, upstream_key

    extra = extra or {}
    expected, mapped = model.state_dict(), {}
    for key, value in state.items():
        name = extra.get(key) or (seqvpr_name(key[len(prefix):]) if key.startswith(prefix) else None)
        name = name if name is None or key in extra else target + name
        if name not in expected:
            raise SeqvprError(f"{path}: a {title} checkpoint with an unexpected key {key!r}")
        need = expected[name].shape
        if value.shape != need and not value.numel() == expected[name].numel() == 1:
            raise SeqvprError(f"{path}: {key} has shape {tuple(value.shape)}, the model needs {tuple(need)}")
        mapped[name] = value.reshape(need)
    buffers = {target + name for name in INPUT_BUFFERS}  # seqvpr's input normalisation, not in the file
    missing = [name for name in expected if name not in mapped and name not in buffers]
    if missing:
        inverse = {v: k for k, v in extra.items()}
        first = inverse.get(missing[0]) or prefix + upstream_key(missing[0].removeprefix(target))
        raise SeqvprError(f"{path}: a {title} checkpoint with a missing key {first!r}")
    return {**{name: expected[name] for name in buffers}, **mapped}


def head_backbone(state: dict[str, torch.Tensor], prefix: str, path: Path, title: str) -> tuple[str, int]:
    """The ResNet (by the CosPlace head's input size: 512 -> ResNet-18, 2048 -> ResNet-50) and the output size."""
    from seqvpr.models.cosplace import BACKBONE_OF_CHANNELS

    key = prefix + "aggregation.3.weight"
    head = state.get(key)
    if head is None:
        raise SeqvprError(f"{path}: a {title} checkpoint with a missing key {key!r}")
    backbone = BACKBONE_OF_CHANNELS.get(int(head.shape[1])) if head.ndim == 2 else None
    if backbone is None:
        raise SeqvprError(f"{path}: {key} has shape {tuple(head.shape)}; expected [dim, 512] (ResNet-18) or "
                          f"[dim, 2048] (ResNet-50)")
    return backbone, int(head.shape[0])


def save_published_cosplace(state: dict[str, torch.Tensor], out: str | Path, source: dict, path: Path) -> Path:
    """The CosPlace encoder of a published file (ResNet-18/50 by the head's input size) with upstream's forward;
    images at ``cosplace.DEFAULT_IMAGE_SIZE`` (recorded in the folder)."""
    from seqvpr.models.cosplace import DEFAULT_IMAGE_SIZE, build_cosplace, save_cosplace

    backbone, out_dim = head_backbone(state, "", path, "CosPlace")
    encoder = build_cosplace(backbone, out_dim)
    encoder.load_state_dict(cosplace_state(state, encoder, path), strict=True)
    return save_cosplace(out, encoder, backbone, {"image_size": list(DEFAULT_IMAGE_SIZE), **source})


def save_published_jist(
    state: dict[str, torch.Tensor], out: str | Path, length: int, source: dict, path: Path
) -> Path:
    """The JIST model of a published file (ResNet-18/50 by the head's input size), with upstream's forward: SeqGeM
    without final normalisation, images at 480 x 640."""
    from seqvpr.models.configs import JistConfig
    from seqvpr.models.jist import build_jist, save_jist

    backbone, out_dim = head_backbone(state, JIST_PREFIX, path, "JIST")
    config = JistConfig(backbone=backbone, out_dim=out_dim, seq_length=length, seqgem_normalize=False)
    model = build_jist(config)
    mapped = cosplace_state(state, model, path, "JIST", prefix=JIST_PREFIX, target="encoder.",
                            extra={JIST_POOL: "sequence_pool.p"})
    model.load_state_dict(mapped, strict=True)
    return save_jist(out, model, config, {"image_size": list(JIST_IMAGE_SIZE), "sequence": {"length": length},
                                          **source})

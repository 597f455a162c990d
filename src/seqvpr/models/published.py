"""Published checkpoints of the reference codes, converted into seqvpr model folders, strictly.

Containers: a raw ``state_dict``; SeqNet/SeqMatchNet training checkpoints (``{"epoch", "state_dict", "recalls",
"best_score", ...}``, whose numpy float64 scalars load through an allow-list, never through unrestricted
unpickling); CosPlace/JIST training checkpoints (``model_state_dict``). Prefixes ``module.`` (DataParallel) and
``pool.module.`` (SeqMatchNet on several GPUs) are removed. Kinds converted so far: SeqNet (``pool.0.conv.*``,
any w) and SeqMatchNet (``pool.1.conv.*``, kernel 1 = the per-frame transform ``normalize(W x + B)``, with
upstream's forward: no input normalisation). A missing or unexpected key, or a wrong shape, is a one-line error
naming it; the folder records the source file and its sha256. JIST (``JIST_r18_512_seqgem.pth``, ``best_model.pth``:
the 123 CosPlace keys under ``model.`` plus ``seq_gem.p``) becomes a JIST folder with upstream's forward: SeqGeM
without final normalisation (searched by exact L2), images at 480 x 640.
"""

from __future__ import annotations

import hashlib
import json
import pickle
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from seqvpr.errors import SeqvprError

PREFIXES = (("module.", ""), ("pool.module.", "pool."))
KINDS_KEYS = {
    "seqnet": ("pool.0.conv.weight", "pool.0.conv.bias"),
    "seqmatchnet": ("pool.1.conv.weight", "pool.1.conv.bias"),
}
NOT_YET = {"aggregation.3.weight": "CosPlace"}
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
    path = Path(path)
    if not path.is_file():
        raise SeqvprError(f"{path}: no such checkpoint file")
    try:
        with torch.serialization.safe_globals(numpy_scalar_globals()):
            content = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, OSError, ValueError) as error:
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
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
    """The published model a state dict is, by its keys; exactly its keys, or a one-line error naming one."""
    if JIST_POOL in state:
        return "jist"
    for kind, keys in KINDS_KEYS.items():
        if keys[0] in state:
            unexpected = sorted(set(state) - set(keys))
            missing = [k for k in keys if k not in state]
            if unexpected or missing:
                which = f"unexpected key {unexpected[0]!r}" if unexpected else f"missing key {missing[0]!r}"
                raise SeqvprError(f"{path}: a {kind} checkpoint with an {which}")
            return kind
    for key, name in NOT_YET.items():
        if any(k.endswith(key) for k in state):
            raise SeqvprError(f"{path}: a {name} checkpoint; importing {name} files is not available yet")
    raise SeqvprError(f"{path}: not a SeqNet or SeqMatchNet checkpoint (no key {' or '.join(k[0] for k in KINDS_KEYS.values())!r})")


def read_flags(path: str | Path | None) -> dict[str, Any]:
    """The run's ``flags.json`` (seqL, w, outDims...), or nothing."""
    if path is None:
        return {}
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
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def import_checkpoint(path: str | Path, out: str | Path, flags_path: str | Path | None = None) -> ImportedModel:
    """Convert a published SeqNet or SeqMatchNet checkpoint into a seqvpr model folder ``out``."""
    from seqvpr.models.configs import TransformConfig
    from seqvpr.models.seqmatchnet import FrameTransform, save_seqmatchnet
    from seqvpr.models.seqnet import save_seqnet
    from seqvpr.sequences.descriptors import SeqNet

    path = Path(path)
    state = state_dict_of(read_container(path), path)
    kind, flags = detect_kind(state, path), read_flags(flags_path)
    sha = file_sha256(path)
    if kind == "jist":
        source = {"source": {"file": str(path), "sha256": sha, "flags": flags or None}}
        save_published_jist(state, out, int(flags.get("seq_length") or 5), source, path)
        return ImportedModel(kind, Path(out), sha)
    prefix = KINDS_KEYS[kind][0].rsplit(".", 1)[0]
    out_dim, in_dim, w = conv_shapes(state, prefix, path)
    check_flag(flags, "outDims", out_dim, path, flags_path)
    source = {"source": {"file": str(path), "sha256": sha, "flags": flags or None}}
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


def jist_state(state: dict[str, torch.Tensor], model: torch.nn.Module, path: Path) -> dict[str, torch.Tensor]:
    """A published JIST state dict (the CosPlace keys under ``model.``, plus ``seq_gem.p``) in the seqvpr JIST
    model's names, strictly: every file key has a place and every model parameter a file key."""
    from seqvpr.features.backbones import COSPLACE_CHILDREN

    heads = {"aggregation.1.p": "encoder.gem.p", "aggregation.3.weight": "encoder.fc.weight",
             "aggregation.3.bias": "encoder.fc.bias"}
    mapped: dict[str, torch.Tensor] = {"sequence_pool.p": state[JIST_POOL]}
    for key, value in state.items():
        if key == JIST_POOL:
            continue
        name = key.removeprefix(JIST_PREFIX)
        child, _, rest = name.removeprefix("backbone.").partition(".")
        if name in heads:
            mapped[heads[name]] = value
        elif name.startswith("backbone.") and child in COSPLACE_CHILDREN:
            mapped[f"encoder.backbone.{COSPLACE_CHILDREN[child]}.{rest}"] = value
        else:
            raise SeqvprError(f"{path}: a JIST checkpoint with an unexpected key {key!r}")
    expected = model.state_dict()
    for name, value in mapped.items():
        if name not in expected:
            raise SeqvprError(f"{path}: a JIST checkpoint with an unexpected key for {name!r}")
        if value.numel() != expected[name].numel():
            raise SeqvprError(f"{path}: {name} has shape {tuple(value.shape)}, the model needs {tuple(expected[name].shape)}")
        mapped[name] = value.reshape(expected[name].shape)
    buffers = {"encoder.mean", "encoder.std"}  # seqvpr's input normalisation, not in the file
    missing = [name for name in expected if name not in mapped and name not in buffers]
    if missing:
        raise SeqvprError(f"{path}: a JIST checkpoint with a missing key {upstream_jist_key(missing[0], heads)!r}")
    return {**{name: expected[name] for name in buffers}, **mapped}


def upstream_jist_key(name: str, heads: dict[str, str]) -> str:
    """The upstream key of a seqvpr JIST parameter name (for naming a missing key as the file would)."""
    from seqvpr.features.backbones import COSPLACE_CHILDREN

    if name == "sequence_pool.p":
        return JIST_POOL
    inverse = {v: k for k, v in heads.items()}
    if name in inverse:
        return JIST_PREFIX + inverse[name]
    child, _, rest = name.removeprefix("encoder.backbone.").partition(".")
    index = {v: k for k, v in COSPLACE_CHILDREN.items()}.get(child, child)
    return f"{JIST_PREFIX}backbone.{index}.{rest}"


def save_published_jist(
    state: dict[str, torch.Tensor], out: str | Path, length: int, source: dict, path: Path
) -> Path:
    """The JIST model of a published file (ResNet-18/50 by the head's input size), with upstream's forward: SeqGeM
    without final normalisation, images at 480 x 640."""
    from seqvpr.models.configs import JistConfig
    from seqvpr.models.jist import build_jist, save_jist
    from seqvpr.sequences.descriptors import SeqGeM

    head = state.get(JIST_PREFIX + "aggregation.3.weight")
    if head is None or head.ndim != 2:
        raise SeqvprError(f"{path}: a JIST checkpoint with a missing key {JIST_PREFIX + 'aggregation.3.weight'!r}")
    backbone = {512: "resnet18", 2048: "resnet50"}.get(int(head.shape[1]))
    if backbone is None:
        raise SeqvprError(f"{path}: aggregation.3.weight takes {head.shape[1]}-D features; expected 512 or 2048")
    config = JistConfig(backbone=backbone, out_dim=int(head.shape[0]), seq_length=length)
    model = build_jist(config, SeqGeM(normalize=False))
    model.load_state_dict(jist_state(state, model, path), strict=True)
    return save_jist(out, model, config, {"image_size": list(JIST_IMAGE_SIZE), "sequence": {"length": length},
                                          **source})

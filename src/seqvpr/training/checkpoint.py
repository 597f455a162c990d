"""Checkpoints as safetensors weights plus a JSON config: everything needed to apply or resume a model.

A model folder holds ``model.safetensors`` and ``config.json``. A resumable run also holds
``train_state.safetensors`` (optimizer buffers, miner cache) and ``train_state.json`` (epoch, scheduler,
history). Files are written to a temporary name and renamed, so a killed run never leaves a half-written file.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save

from seqvpr.errors import SeqvprError
from seqvpr.io import atomic_write
from seqvpr.models.seqmatchnet import FrameTransform, TransformConfig

MODEL_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
STATE_FILE = "train_state.safetensors"
STATE_JSON = "train_state.json"
FORMAT = "seqvpr-seqmatchnet"


def save_tensors(path: Path, tensors: dict[str, torch.Tensor]) -> None:
    """safetensors file written atomically (contiguous CPU copies)."""
    payload = save({k: v.detach().cpu().contiguous() for k, v in tensors.items()})
    with atomic_write(path, "wb") as handle:
        handle.write(payload)


def save_json(path: Path, values: dict[str, Any]) -> None:
    with atomic_write(path) as handle:
        json.dump(values, handle, indent=2, default=str)


def read_json(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise SeqvprError(f"{path}: no such file") from None
    except json.JSONDecodeError as error:
        raise SeqvprError(f"{path}: not valid JSON ({error.msg}, line {error.lineno})") from None


def read_tensors(path: Path) -> dict[str, torch.Tensor]:
    if not path.is_file():
        raise SeqvprError(f"{path}: no such file")
    try:
        return load_file(str(path))
    except (SafetensorError, OSError) as error:
        raise SeqvprError(f"{path}: not a readable safetensors file ({error})") from None


def save_model(folder: str | Path, model: FrameTransform, metadata: dict[str, Any]) -> Path:
    """Write the transform's weights and config (plus ``metadata``: sequence length, training settings...)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    save_tensors(folder / MODEL_FILE, model.state_dict())
    save_json(folder / CONFIG_FILE, {"format": FORMAT, "transform": model.config.as_dict(), **metadata})
    return folder


def load_model(folder: str | Path) -> tuple[FrameTransform, dict[str, Any]]:
    """The transform saved in ``folder`` and its config; a one-line error when something is missing or wrong."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SeqvprError(f"{folder}: no such model folder (expected {MODEL_FILE} and {CONFIG_FILE} inside)")
    config = read_json(folder / CONFIG_FILE)
    if config.get("format") != FORMAT or "transform" not in config:
        raise SeqvprError(f"{folder / CONFIG_FILE}: not a seqvpr SeqMatchNet config (format {config.get('format')!r})")
    model = FrameTransform(TransformConfig.from_dict(config["transform"]))
    weights = read_tensors(folder / MODEL_FILE)
    try:
        model.load_state_dict(weights, strict=True)
    except RuntimeError as error:
        raise SeqvprError(f"{folder / MODEL_FILE}: weights do not fit the config ({str(error).splitlines()[0]})") from None
    return model.eval(), config


def flatten_optimizer(state: dict[str, Any]) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """An optimizer state_dict split into tensors (for safetensors) and the JSON-able rest."""
    tensors: dict[str, torch.Tensor] = {}
    scalars: dict[str, dict[str, Any]] = {}
    for index, values in state["state"].items():
        for key, value in values.items():
            if torch.is_tensor(value):
                tensors[f"optimizer.{index}.{key}"] = value
            else:
                scalars.setdefault(str(index), {})[key] = value
    return tensors, {"param_groups": state["param_groups"], "scalars": scalars}


def unflatten_optimizer(tensors: dict[str, torch.Tensor], rest: dict[str, Any]) -> dict[str, Any]:
    """Inverse of ``flatten_optimizer``."""
    state: dict[int, dict[str, Any]] = {}
    for name, value in tensors.items():
        if name.startswith("optimizer."):
            _, index, key = name.split(".", 2)
            state.setdefault(int(index), {})[key] = value
    for index, values in rest["scalars"].items():
        state.setdefault(int(index), {}).update(values)
    return {"state": state, "param_groups": rest["param_groups"]}

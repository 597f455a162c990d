"""A model folder on disk: ``model.safetensors`` (weights) plus ``config.json`` (format name and everything needed
to rebuild the module). Files are written to a temporary name and renamed, so a killed run never leaves half a file.
``config.json`` is written last and records its version and the weights' digest (``files``): loading checks it, so
weights and a config from different runs are refused (folders written before the digest was recorded still load).

Same name as ``seqvpr.maps.files``: the same concept (an artifact's folder on disk) for a model; a map's there.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save

from seqvpr.errors import SeqvprError
from seqvpr.identity import check_digest, seal_files
from seqvpr.io import atomic_write

MODEL_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
#: the model folder's layout version, in ``config.json`` (absent: a folder from before the weights' digest)
MODEL_VERSION = 1


def save_tensors(path: Path, tensors: dict[str, torch.Tensor]) -> None:
    """safetensors file written atomically (contiguous CPU copies)."""
    payload = save({k: v.detach().cpu().contiguous() for k, v in tensors.items()})
    with atomic_write(path, "wb") as handle:
        handle.write(payload)


def save_json(path: Path, values: dict[str, Any]) -> None:
    with atomic_write(path) as handle:
        json.dump(values, handle, indent=2, default=str)


def read_json(path: Path) -> dict[str, Any]:
    from seqvpr.arrays import check_regular_file

    try:
        return json.loads(check_regular_file(path, "a JSON file").read_text())
    except FileNotFoundError:
        raise SeqvprError(f"{path}: no such file") from None
    except json.JSONDecodeError as error:
        raise SeqvprError(f"{path}: not valid JSON ({error.msg}, line {error.lineno})") from None
    except UnicodeDecodeError as error:
        raise SeqvprError(f"{path}: not valid JSON (not UTF-8 text at byte {error.start})") from None


def read_tensors(path: Path) -> dict[str, torch.Tensor]:
    if not path.is_file():
        raise SeqvprError(f"{path}: no such file")
    try:
        return load_file(str(path))
    except (SafetensorError, OSError) as error:
        raise SeqvprError(f"{path}: not a readable safetensors file ({error})") from None


def save_model_folder(folder: str | Path, module: torch.nn.Module, config: dict[str, Any]) -> Path:
    """Write ``module``'s weights, then ``config`` (which names its format) with the weights' digest, into
    ``folder``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    save_tensors(folder / MODEL_FILE, module.state_dict())
    save_json(folder / CONFIG_FILE, {**config, "version": MODEL_VERSION, "files": seal_files(folder, [MODEL_FILE])})
    return folder


def read_model_config(folder: str | Path, format_name: str | None = None, title: str = "model") -> dict[str, Any]:
    """The ``config.json`` of a model folder; with ``format_name``, a folder of another format is an error."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SeqvprError(f"{folder}: no such model folder (expected {MODEL_FILE} and {CONFIG_FILE} inside)")
    config = read_json(folder / CONFIG_FILE)
    if not isinstance(config, dict):
        raise SeqvprError(f"{folder / CONFIG_FILE}: not a seqvpr model config (not a JSON object)")
    if config.get("version", MODEL_VERSION) != MODEL_VERSION:
        raise SeqvprError(f"{folder / CONFIG_FILE}: model folder version {config.get('version')!r} is not known (this "
                          f"seqvpr reads version {MODEL_VERSION})")
    if format_name is not None and config.get("format") != format_name:
        raise SeqvprError(f"{folder / CONFIG_FILE}: not a seqvpr {title} config (format {config.get('format')!r})")
    return config


def load_weights_into(module: torch.nn.Module, folder: str | Path) -> torch.nn.Module:
    """``module`` (in eval mode) with the folder's weights, strictly: a key or shape that does not fit is a
    one-line error naming the file, and so are weights that are not the ones ``config.json`` records."""
    path = Path(folder) / MODEL_FILE
    check_model_files(folder)
    try:
        module.load_state_dict(read_tensors(path), strict=True)
    except RuntimeError as error:
        raise SeqvprError(f"{path}: weights do not fit the config ({str(error).splitlines()[0]})") from None
    return module.eval()


def check_model_files(folder: str | Path) -> None:
    """The files ``config.json`` records (the weights, and any other file of the model) hold what it says: one
    line naming the first that does not. A config without a record (an older folder) checks nothing."""
    folder = Path(folder)
    recorded = read_model_config(folder).get("files")
    if recorded is None:
        return
    if not isinstance(recorded, dict) or not all(isinstance(v, str) for v in recorded.values()):
        raise SeqvprError(f"{folder / CONFIG_FILE}: 'files' must map file names to digests")
    for name, digest in recorded.items():
        if Path(name).name != name:
            raise SeqvprError(f"{folder / CONFIG_FILE}: 'files' names {name!r}, not a file of the folder")
        check_digest(folder / name, digest, str(folder / CONFIG_FILE))

"""One record per model kind: its format name in ``config.json``, what it consumes, the method it implies, and its
model file's save and load; ``load_trained_model(folder)`` loads any trained model folder by its format, and
``load_models(folders)`` a set of them by kind (one per kind), as every entry point takes them.

Adding a model kind is one module in ``models/`` (the module, ``save_<kind>``, ``load_<kind>``) and one record
here; ``seqvpr match --model`` and every library entry point then know it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch

from seqvpr.errors import SeqvprError, SettingError
from seqvpr.models import cosplace, jist, seqmatchnet, seqnet
from seqvpr.models.files import CONFIG_FILE, read_model_config


@dataclass(frozen=True)
class TrainedModel:
    """A loaded model folder: its kind, the module (eval mode), its sequence length and, for a model that consumes
    images (JIST, CosPlace: a single-image frame encoder of length 1), the image size it reads them at."""

    kind: str
    module: torch.nn.Module
    length: int
    folder: Path
    image_size: tuple[int, int] | None = None


@dataclass(frozen=True)
class ModelKind:
    """A kind of trained model. ``consumes``: frame descriptors, or images (the model describes them itself);
    ``method``: the method a folder of this kind implies in ``seqvpr match --model``."""

    name: str
    title: str
    format: str
    consumes: Literal["descriptors", "images"]
    method: str
    save: Callable[..., Any]
    load: Callable[[Path, str], TrainedModel]


def _load_seqmatchnet(folder: Path, device: str) -> TrainedModel:
    module, config = seqmatchnet.load_seqmatchnet(folder)
    return TrainedModel("seqmatchnet", module, int(config.get("sequence", {}).get("length", 1)), folder)


def _load_seqnet(folder: Path, device: str) -> TrainedModel:
    module, config = seqnet.load_seqnet(folder)
    return TrainedModel("seqnet", module, int(config.get("L") or module.w), folder)


def _on_device(module: torch.nn.Module, device: str) -> torch.nn.Module:
    try:
        return module.to(device)
    except (RuntimeError, AssertionError) as error:
        raise SeqvprError(f"device {device!r} is not usable here ({str(error).splitlines()[0]})") from None


def _load_jist(folder: Path, device: str) -> TrainedModel:
    meta = read_model_config(folder, jist.FORMAT, "JIST")
    module = _on_device(jist.load_jist(folder), device)
    return TrainedModel("jist", module, int(meta["config"]["seq_length"]), folder, jist.jist_image_size(meta))


def _load_cosplace(folder: Path, device: str) -> TrainedModel:
    encoder, meta = cosplace.load_cosplace(folder)
    encoder = _on_device(encoder, device)
    return TrainedModel("cosplace", encoder, 1, folder, cosplace.cosplace_image_size(meta))


MODEL_KINDS: dict[str, ModelKind] = {kind.name: kind for kind in (
    ModelKind("seqmatchnet", "SeqMatchNet", seqmatchnet.FORMAT, "descriptors", "seqmatchnet",
              seqmatchnet.save_seqmatchnet, _load_seqmatchnet),
    ModelKind("seqnet", "SeqNet", seqnet.FORMAT, "descriptors", "seqnet", seqnet.save_seqnet, _load_seqnet),
    ModelKind("jist", "JIST", jist.FORMAT, "images", "jist", jist.save_jist, _load_jist),
    ModelKind("cosplace", "CosPlace", cosplace.FORMAT, "images", "single", cosplace.save_cosplace, _load_cosplace),
)}


def model_kind(folder: str | Path) -> ModelKind:
    """The kind of a model folder, from the ``format`` in its config.json."""
    config = read_model_config(folder)
    found = config.get("format")
    for kind in MODEL_KINDS.values():
        if kind.format == found:
            return kind
    formats = ", ".join(kind.format for kind in MODEL_KINDS.values())
    raise SeqvprError(f"{Path(folder) / CONFIG_FILE}: unknown model format {found!r} (expected one of: {formats})")


def load_trained_model(folder: str | Path, device: str = "cpu") -> TrainedModel:
    """Any trained model folder (``seqvpr train --out``), loaded by its kind; one-line errors when it is wrong."""
    folder = Path(folder)
    return model_kind(folder).load(folder, device)


def model_kinds(folders: Iterable[str | Path]) -> dict[str, Path]:
    """Each model folder by its kind, read from its config alone (no weights loaded): one folder per kind, a
    second of a kind is a one-line error."""
    kinds: dict[str, Path] = {}
    for folder in folders:
        kind = model_kind(folder).name
        if kind in kinds:
            raise SettingError(f"{{models}}: {folder} is a second {kind} model (give one model per kind)")
        kinds[kind] = Path(folder)
    return kinds


def load_models(folders: Iterable[str | Path], device: str = "cpu") -> dict[str, TrainedModel]:
    """Model folders loaded by kind (one per kind): what every entry point that takes models loads them with."""
    return {kind: load_trained_model(folder, device) for kind, folder in model_kinds(folders).items()}

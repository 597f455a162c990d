"""The SeqNet model folder: a ``sequences.descriptors.SeqNet`` (temporal Conv1d sequence descriptor) with its
input/output sizes, kernel width and sequence length.

Same name as ``seqvpr.training.seqnet``: SeqNet's model; its learner there."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from seqvpr.errors import SeqvprError
from seqvpr.models.files import CONFIG_FILE, load_weights_into, read_model_config, save_model_folder
from seqvpr.sequences.descriptors import SeqNet

FORMAT = "seqvpr-seqnet"


def save_seqnet(folder: str | Path, model: SeqNet, metadata: dict[str, Any] | None = None) -> Path:
    """``model.safetensors`` + ``config.json`` (format, in_dim, out_dim, w, L, then ``metadata``), written
    atomically."""
    metadata = dict(metadata or {})
    length = metadata.get("sequence", {}).get("length")
    config = {"format": FORMAT, "in_dim": model.in_dim, "out_dim": model.out_dim, "w": model.w, "L": length, **metadata}
    return save_model_folder(folder, model, config)


def load_seqnet(folder: str | Path) -> tuple[SeqNet, dict[str, Any]]:
    """The SeqNet saved in ``folder`` (in eval mode) and its config; one-line errors when missing or wrong."""
    config = read_model_config(folder, FORMAT, "SeqNet")
    try:
        model = SeqNet(int(config["in_dim"]), int(config["out_dim"]), int(config["w"]))
    except (KeyError, TypeError, ValueError) as error:
        raise SeqvprError(f"{Path(folder) / CONFIG_FILE}: SeqNet config lacks a valid {error}") from None
    return load_weights_into(model, folder), config

"""SeqMatchNet's learnable per-frame descriptor transform, X' = normalize(W X + B), and its deeper MLP variant.

Every frame is transformed independently (no temporal mixing); the sequence structure enters only through the
loss and the miner, which use the matching kernel's sequence distance.

Same name as ``seqvpr.training.seqmatchnet``: SeqMatchNet's model; its learner there.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from seqvpr.errors import SeqvprError
from seqvpr.models.configs import Init, TransformConfig
from seqvpr.models.files import CONFIG_FILE, load_weights_into, read_model_config, save_model_folder




class FrameTransform(nn.Module):
    """normalize(W x + B) per frame (or an MLP with ReLUs before the last layer); input rows [..., in_dim]."""

    def __init__(self, config: TransformConfig, seed: int = 0) -> None:
        super().__init__()
        self.config = config
        sizes = (config.in_dim, *config.hidden, config.output_dim)
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:]))
        generator = torch.Generator().manual_seed(seed)
        for layer in self.layers:
            _initialize(layer, config.init, generator)

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        if frames.shape[-1] != self.config.in_dim:
            raise SeqvprError(
                f"the model expects {self.config.in_dim}-D descriptors, got {frames.shape[-1]}-D"
            )
        x = nn.functional.normalize(frames, dim=-1) if self.config.normalize_input else frames
        for number, layer in enumerate(self.layers):
            x = layer(x)
            if number < len(self.layers) - 1:
                x = torch.relu(x)
        return nn.functional.normalize(x, dim=-1)


def _initialize(layer: nn.Linear, init: Init, generator: torch.Generator) -> None:
    """Seeded initialisation: PyTorch's default for Linear/Conv1d, or identity-like with zero bias."""
    with torch.no_grad():
        if init == "reference":
            nn.init.kaiming_uniform_(layer.weight, a=math.sqrt(5), generator=generator)
            bound = 1.0 / math.sqrt(layer.in_features)
            nn.init.uniform_(layer.bias, -bound, bound, generator=generator)
            return
        if layer.in_features == layer.out_features:
            layer.weight.copy_(torch.eye(layer.out_features))
        else:
            nn.init.orthogonal_(layer.weight, generator=generator)
        layer.bias.zero_()


def apply_transform(
    model: FrameTransform, descriptors: np.ndarray | torch.Tensor, batch_size: int = 4096, device: str = "cpu"
) -> np.ndarray:
    """Transformed descriptors [N, out_dim] as float32 numpy, computed in batches without gradients."""
    model = model.to(device).eval()
    out = np.empty((len(descriptors), model.config.output_dim), dtype=np.float32)
    with torch.no_grad():
        for begin in range(0, len(descriptors), batch_size):
            rows = descriptors[begin : begin + batch_size]  # a batch at a time: a memory-mapped map is never copied
            rows = rows if torch.is_tensor(rows) else torch.from_numpy(np.array(rows, dtype=np.float32))
            batch = rows.to(device=device, dtype=torch.float32)
            out[begin : begin + batch_size] = model(batch).cpu().numpy()
    return out


# --- model folder ------------------------------------------------------------------------------------------------

FORMAT = "seqvpr-seqmatchnet"


def save_seqmatchnet(folder: str | Path, model: FrameTransform, metadata: dict[str, Any]) -> Path:
    """Write the transform's weights and config (plus ``metadata``: sequence length, training settings...)."""
    return save_model_folder(folder, model, {"format": FORMAT, "transform": model.config.as_dict(), **metadata})


def load_seqmatchnet(folder: str | Path) -> tuple[FrameTransform, dict[str, Any]]:
    """The transform saved in ``folder`` (eval mode) and its config; a one-line error when something is wrong."""
    config = read_model_config(folder, FORMAT, "SeqMatchNet")
    if "transform" not in config:
        raise SeqvprError(f"{Path(folder) / CONFIG_FILE}: not a seqvpr SeqMatchNet config (no 'transform')")
    model = FrameTransform(TransformConfig.from_dict(config["transform"]))
    return load_weights_into(model, folder), config

"""Inference engines for an image encoder: torch as built, or ONNX Runtime's CPU engine over the same network.

On a CPU, ONNX Runtime runs EfficientNet-Lite0 + GeM at 320x240 in about half torch's time with descriptors equal to
1e-6 (BENCHMARKS, "What a frame costs"), and a robot's frame rate is set by its encoder. The network is exported
once per encoder identity (its weights and buffers, input size, torch version), kept in seqvpr's cache folder
(``encoders/``), and checked against torch on a probe batch when it is made: an export that differs by more than
``TOLERANCE`` is never used. ``auto`` takes ONNX Runtime on the CPU when it is installed and the encoder exports,
torch otherwise (and always on a GPU). ONNX Runtime's pools follow the one thread policy (``seqvpr.threads``).
"""

from __future__ import annotations

import hashlib
import logging
import os
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from seqvpr import checks
from seqvpr.errors import SeqvprError, SettingError

ENGINES = checks.ENGINES
#: the largest difference (max abs over a probe batch's descriptors) an export may show against torch
TOLERANCE = 1e-5
OPSET = 17
#: how seqvpr writes an export (bumped when the graph it writes changes, so a cached export of an older kind is remade)
EXPORT_REVISION = 2
INPUT, OUTPUT = "images", "descriptors"
LOGGER = logging.getLogger("seqvpr")
Normalization = tuple[tuple[float, ...], tuple[float, ...]]
INSTALL = "pip install onnxruntime onnx (both come with seqvpr; a slim install may lack them)"


def onnx_runtime_installed() -> bool:
    """Whether ONNX Runtime (to run) and onnx (to export) can be imported."""
    import importlib.util

    return all(importlib.util.find_spec(name) is not None for name in ("onnxruntime", "onnx"))


def check_engine(engine: Any) -> str:
    """``engine`` one of ``ENGINES``; ``onnx`` where ONNX Runtime is absent is one line saying how to install it."""
    checks.text(engine, "engine", ENGINES)
    if engine == "onnx" and not onnx_runtime_installed():
        raise SettingError(f"{{engine}} onnx needs ONNX Runtime: {INSTALL}")
    return engine


class OnnxEncoder:
    """An encoder run by ONNX Runtime on the CPU, called as the torch module was: images [B, 3, H, W] in [0, 1] ->
    descriptors [B, D] (float32 tensors). ``source`` names the file in errors."""

    def __init__(self, path: str | Path, threads: int | None = None, source: str | None = None) -> None:
        self.path, self.source = Path(path), source or str(path)
        self.session = open_session(self.path, threads)
        self.input = self.session.get_inputs()[0].name
        self.normalization: tuple[torch.Tensor, torch.Tensor] | None = None

    def with_threads(self, threads: int) -> OnnxEncoder:
        """The same file in a session of ``threads`` intra-op threads (a batch runs one-thread sessions side by
        side); this one when it already has that many."""
        if self.session.get_session_options().intra_op_num_threads == threads:
            return self
        other = OnnxEncoder(self.path, threads, self.source)
        other.normalization = self.normalization
        return other

    def normalize_with(self, normalization: Normalization) -> None:
        """Images are normalised with (mean, std) before the model (a user's file expects its own)."""
        mean, std = (torch.tensor(v, dtype=torch.float32).view(1, 3, 1, 1) for v in normalization)
        self.normalization = mean, std

    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        images = images.detach().to("cpu", torch.float32)
        if self.normalization is not None:
            images = (images - self.normalization[0]) / self.normalization[1]
        batch = images.contiguous().numpy()
        try:
            out = self.session.run(None, {self.input: batch})[0]
        except Exception as error:  # noqa: BLE001 - ONNX Runtime's own error classes: one line naming the file
            raise SeqvprError(f"{self.source}: ONNX Runtime failed on a batch of shape {list(batch.shape)} "
                              f"({str(error).splitlines()[0][:200]})") from None
        return torch.from_numpy(np.asarray(out, dtype=np.float32))

    training = False  # the torch module's interface, where callers set it up: an export is fixed in eval mode

    def eval(self) -> OnnxEncoder:
        return self

    def train(self, mode: bool = True) -> OnnxEncoder:
        return self

    def to(self, *args: Any, **kwargs: Any) -> OnnxEncoder:
        return self


def load_onnx_encoder(path: str | Path, width: int, height: int, normalization: Normalization | None,
                      default: Normalization) -> OnnxEncoder:
    """A user's ONNX encoder (``--descriptor onnx:PATH``), checked at load: one float input [B, 3, H, W] whose
    fixed sides are ``width`` x ``height``, and a float [B, D] output on a probe image; one line naming the file
    otherwise. ``normalization`` (mean, std) is applied before it; None: the file's own contract (a seqvpr export
    takes pixels in [0, 1]) or else ``default``."""
    path = Path(path)
    if not path.is_file():
        raise SeqvprError(f"{path}: no such ONNX file")
    encoder = OnnxEncoder(path)
    own = "seqvpr.input" in encoder.session.get_modelmeta().custom_metadata_map
    encoder.normalize_with(normalization or (((0.0,) * 3, (1.0,) * 3) if own else default))
    inputs = encoder.session.get_inputs()
    if len(inputs) != 1:
        raise SeqvprError(f"{path}: the model has {len(inputs)} inputs ({', '.join(i.name for i in inputs)}); seqvpr "
                          "feeds one [batch, 3, height, width] image batch")
    check_input(path, inputs[0], width, height)
    probe = torch.rand(1, 3, height, width, generator=torch.Generator().manual_seed(0))
    raw = encoder.session.run(None, {encoder.input: probe.numpy()})[0]
    if not np.issubdtype(np.asarray(raw).dtype, np.floating) or np.ndim(raw) != 2 or len(raw) != 1:
        raise SeqvprError(f"{path}: the model returned {np.asarray(raw).dtype} {list(np.shape(raw))} for one image; "
                          "expected float [batch, dim] descriptors (pool and flatten inside the model)")
    return encoder


def check_input(path: Path, given: Any, width: int, height: int) -> None:
    """The ONNX input takes float [B, 3, H, W] images at this size (a side given as a name is free)."""
    shape = list(given.shape)
    if given.type != "tensor(float)" or len(shape) != 4 or shape[1] not in (3, None) and not isinstance(shape[1], str):
        raise SeqvprError(f"{path}: its input {given.name} is {given.type} {shape}; seqvpr feeds float "
                          "[batch, 3, height, width] images")
    fixed = [side if isinstance(side, int) else None for side in shape[2:]]
    if any(side is not None and side != want for side, want in zip(fixed, (height, width))):
        raise SeqvprError(f"{path}: the model takes {shape[3]}x{shape[2]} images (width x height), not {width}x{height}:"
                          f" give --image-size {shape[3]}x{shape[2]}")


def input_size(path: str | Path) -> tuple[int, int] | None:
    """The (width, height) an ONNX file's input fixes, or None where a side is free (a name, not a number)."""
    import onnx

    try:
        model = onnx.load(str(path), load_external_data=False)
        dims = model.graph.input[0].type.tensor_type.shape.dim
    except Exception:  # noqa: BLE001 - unreadable files are refused with their own line when loaded
        return None
    sides = [d.dim_value if d.HasField("dim_value") else None for d in dims][2:]
    return (sides[1], sides[0]) if len(sides) == 2 and all(sides) else None


def open_session(path: Path, threads: int | None = None):
    """An ONNX Runtime CPU session over ``path`` with the thread policy's count in its intra-op pool, one inter-op
    thread and no spinning between calls (a spinning pool takes cores a robot's other processes need)."""
    import onnxruntime

    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = threads or torch.get_num_threads()
    options.inter_op_num_threads = 1
    options.execution_mode = onnxruntime.ExecutionMode.ORT_SEQUENTIAL
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    options.log_severity_level = 3  # errors only: its warnings are about graph rewrites, not the user's input
    try:
        return onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as error:  # noqa: BLE001 - a damaged or unsupported file: one line naming it
        raise SeqvprError(f"{path}: not an ONNX model ONNX Runtime can run ({str(error).splitlines()[0][:200]})") \
            from None


def model_digest(model: nn.Module) -> str:
    """A digest of a module's parameters and buffers, so a cache never outlives a changed (e.g. re-fitted) head."""
    digest = hashlib.sha256()
    for name, tensor in sorted(model.state_dict().items()):
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()[:24]


def encoder_identity(module: nn.Module, width: int, height: int) -> str:
    """What an export depends on: the module's kind, every parameter and buffer (names and values), the input size
    and the torch version and seqvpr's export revision that trace it."""
    digest = hashlib.sha256(f"{type(module).__qualname__}|{width}x{height}|{torch.__version__}|{OPSET}|"
                            f"{EXPORT_REVISION}".encode())
    digest.update(model_digest(module).encode())
    return digest.hexdigest()[:24]


def export_onnx(module: nn.Module, width: int, height: int, out: Path,
                metadata: dict[str, str] | None = None) -> Path:
    """``module`` (images [B, 3, H, W] in [0, 1] -> [B, D]) written to ``out`` as ONNX with a dynamic batch, its input
    contract in the file's metadata; written to a temporary name, then renamed."""
    import onnx

    from seqvpr.io import atomic_write

    probe = torch.rand(1, 3, height, width, generator=torch.Generator().manual_seed(0))
    module = module.to("cpu").eval()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")  # the tracer's notes on Python values it folds into constants
        buffer = _exported_bytes(module, probe)
    model = fusable_pads(onnx.load_from_string(buffer))
    for key, value in {**input_contract(width, height), **(metadata or {})}.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    with atomic_write(out, "wb") as handle:
        handle.write(model.SerializeToString())
    return out


def fusable_pads(model):
    """``model`` with each Pad's omitted optional inputs dropped (torch writes an empty name for them): ONNX Runtime
    folds a zero Pad into the convolution after it only then, which takes a third off EfficientNet-Lite's time on
    a CPU (its TensorFlow "same" padding is a Pad before 17 of its convolutions)."""
    for node in model.graph.node:
        if node.op_type == "Pad":
            while node.input and not node.input[-1]:
                node.input.pop()
    return model


def input_contract(width: int, height: int) -> dict[str, str]:
    """What an exported encoder takes and returns, as its file's metadata says it (``seqvpr.input`` marks a file
    seqvpr wrote: pixels in [0, 1], no normalisation before it)."""
    return {"seqvpr.input": f"float32 [batch, 3, {height}, {width}] RGB in [0, 1]",
            "seqvpr.output": "float32 [batch, dim] descriptors"}


def _exported_bytes(module: nn.Module, probe: torch.Tensor) -> bytes:
    """The module traced to ONNX (opset ``OPSET``, batch axis dynamic), as bytes."""
    import io

    buffer = io.BytesIO()
    torch.onnx.export(module, (probe,), buffer, input_names=[INPUT], output_names=[OUTPUT], opset_version=OPSET,
                      dynamic_axes={INPUT: {0: "batch"}, OUTPUT: {0: "batch"}}, dynamo=False)
    return buffer.getvalue()


def probe_difference(module: Callable, engine: Callable, width: int, height: int) -> float:
    """The largest difference between two encoders' descriptors of a seeded probe batch (two images)."""
    probe = torch.rand(2, 3, height, width, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        return float((module(probe).float() - engine(probe)).abs().max())


def cached_export(module: nn.Module, width: int, height: int, folder: Path | None = None) -> Path:
    """The encoder's ONNX file in the cache (made, and checked against torch within ``TOLERANCE``, if absent)."""
    from seqvpr.cache import cache_folder, writable_folder

    folder = writable_folder(folder or cache_folder("encoders"))
    path = folder / f"{encoder_identity(module, width, height)}.onnx"
    if not path.is_file():
        write_checked(module, width, height, path, lambda made: export_onnx(module, width, height, made), OnnxEncoder)
    return path


def write_checked(module: nn.Module, width: int, height: int, out: Path, write: Callable[[Path], Path],
                  read: Callable[[Path], Callable]) -> float:
    """Write ``module`` as a file (``write`` to a name of this process beside ``out``), read it back (``read``) and
    put it at ``out`` only if its descriptors of a probe batch are within ``TOLERANCE`` of torch's: a file that
    differs never replaces anything (one line). The difference, returned."""
    made = write(out.with_name(f"{out.stem}.{os.getpid()}.unchecked{out.suffix}"))
    try:
        difference = probe_difference(module, read(made), width, height)
        if not difference <= TOLERANCE:
            raise SeqvprError(f"{out}: the exported encoder differs from torch by {difference:.2g} (over "
                              f"{TOLERANCE:g}) on a probe batch: not used")
        made.replace(out)
    finally:
        made.unlink(missing_ok=True)
    return difference


def with_engine(module: nn.Module, width: int, height: int, engine: str = "auto", device: str = "cpu",
                keep: bool = True) -> Any:
    """``module`` as ``engine`` runs it: itself (torch), or an ``OnnxEncoder`` over its cached export (``keep``
    False: exported to a temporary folder, gone once the session holds it). ``auto`` takes ONNX Runtime on the CPU
    where it is installed and the export succeeds and checks out, else torch (a line in the log says why); ``onnx``
    on a GPU or a failed export is one line."""
    check_engine(engine)
    if engine == "torch" or isinstance(module, OnnxEncoder):
        return module
    if not str(device).startswith("cpu"):
        if engine == "onnx":
            raise SettingError(f"{{engine}} onnx runs on the CPU; on {device} give {{engine}} torch or auto")
        return module
    if engine == "auto" and not onnx_runtime_installed():
        LOGGER.info(f"encoder: torch (ONNX Runtime is not installed: {INSTALL})")
        return module
    try:
        if keep:
            return OnnxEncoder(cached_export(module, width, height), source=type(module).__name__)
        import tempfile

        with tempfile.TemporaryDirectory(prefix="seqvpr-encoder-") as folder:
            return OnnxEncoder(cached_export(module, width, height, Path(folder)), source=type(module).__name__)
    except Exception as error:  # noqa: BLE001 - any export failure: auto falls back, onnx says why
        if engine == "onnx":
            raise SettingError(f"{{engine}} onnx: the encoder does not export to ONNX ({_line(error)})") from None
        LOGGER.info(f"encoder: torch (the ONNX export failed: {_line(error)})")
        return module


def _line(error: BaseException) -> str:
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return (lines[0] if lines else type(error).__name__)[:200]

"""Images -> descriptors with a backbone and a pooling head, or a user's TorchScript encoder: batched, with
progress, cached and resumable.

The cache key covers the extractor configuration, the weights file (path, size, mtime; for a TorchScript encoder
its model file) and the image list (path, size, mtime of every image), so a changed model or image set never reuses
a stale cache. Rows are written to a partial file as batches finish; an interrupted run continues from the last
written batch.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from torch import nn

from seqvpr.errors import SeqvprError
from seqvpr.features import backbones
from seqvpr.data.images import read_image
from seqvpr.features.engines import OnnxEncoder, load_onnx_encoder, model_digest, with_engine
from seqvpr.features.pooling import GeM, NetVLAD
from seqvpr.features.torchscript import load_encoder
from seqvpr.io import atomic_write, check_output_apart
from seqvpr.threads import ensure_policy

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
BACKBONES = ("efficientnet-lite0", "resnet18", "resnet50")
TORCHSCRIPT = "torchscript"  # a user's exported encoder: its file is the config's ``weights``
ONNX = "onnx"  # the same, as an ONNX file (run by ONNX Runtime)
FILE_ENCODERS = (TORCHSCRIPT, ONNX)
POOLINGS = ("gem", "netvlad")
CPU_MICRO_BATCH = 2  # images per forward pass on CPU: large batches of depthwise convolutions are slower there


@dataclass(frozen=True)
class ExtractorConfig:
    """Backbone, its weights ('imagenet' or a checkpoint path), pooling ('gem' or 'netvlad' with ``clusters``),
    input size (width, height) and batch size (images read per step; on CPU they go through in micro-batches).

    Backbone ``torchscript`` is a user's exported encoder: ``weights`` is its TorchScript or ``torch.export`` file,
    ``mean``/``std`` its input normalisation (default ImageNet's; built-in backbones use their own and take none),
    and it returns descriptors itself (no pooling head).
    """

    backbone: str = "efficientnet-lite0"
    weights: str | None = "imagenet"
    pooling: str = "gem"
    width: int = 320
    height: int = 240
    batch_size: int = 32
    clusters: int = 64
    mean: tuple[float, float, float] | None = None
    std: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        if self.backbone not in (*BACKBONES, *FILE_ENCODERS):
            raise SeqvprError(f"backbone {self.backbone!r} is not known (choose from: {', '.join(BACKBONES)}, "
                              f"{', '.join(FILE_ENCODERS)})")
        self._check_normalization()
        if self.pooling not in POOLINGS:
            raise SeqvprError(f"pooling {self.pooling!r} is not known (choose from: {', '.join(POOLINGS)})")
        if min(self.width, self.height, self.batch_size) < 1:
            raise SeqvprError("image size and batch size must be positive")
        if self.clusters < 2:
            raise SeqvprError(f"NetVLAD needs at least 2 clusters, got {self.clusters}")

    def _check_normalization(self) -> None:
        """A TorchScript encoder has a model file, no pooling head and a 3-channel mean and positive std; a
        built-in backbone takes no mean/std (it normalises as it was trained)."""
        if self.backbone not in FILE_ENCODERS:
            if self.mean is not None or self.std is not None:
                raise SeqvprError(f"mean/std apply to an encoder file only ({self.backbone} has its own)")
            return
        if self.weights in (None, "imagenet"):
            raise SeqvprError(f"a {self.backbone} encoder needs its model file as weights, got {self.weights!r}")
        if self.pooling != "gem":
            raise SeqvprError(
                f"a {self.backbone} encoder returns descriptors itself; pooling {self.pooling!r} does not apply"
            )
        mean, std = self.normalization()
        if len(mean) != 3 or len(std) != 3 or min(std) <= 0:
            raise SeqvprError(f"mean and std need 3 values each and std must be positive, got {mean} and {std}")

    def normalization(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """A TorchScript encoder's input mean and std (ImageNet's unless set)."""
        return tuple(self.mean or IMAGENET_MEAN), tuple(self.std or IMAGENET_STD)


class Extractor(nn.Module):
    """Backbone feature map -> pooled, L2-normalised descriptor; ``mean``/``std`` normalise [0, 1] pixels.

    GeM pools the backbone's last map (``features``); NetVLAD pools its local features (``local_features``).
    """

    def __init__(self, backbone: nn.Module, pooling: nn.Module, mean: Sequence[float], std: Sequence[float]) -> None:
        super().__init__()
        self.backbone, self.pooling = backbone, pooling
        self.register_buffer("mean", torch.tensor(mean).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(std).view(1, 3, 1, 1))

    def feature_map(self, images: torch.Tensor) -> torch.Tensor:
        """The map the pooling head reads, for images in [0, 1]."""
        normalized = (images - self.mean) / self.std
        if isinstance(self.pooling, NetVLAD):
            return self.backbone.local_features(normalized)
        return self.backbone.features(normalized)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.pooling(self.feature_map(images))


def build_encoder(config: ExtractorConfig) -> nn.Module:
    """The model a configuration describes, images in [0, 1] -> descriptors: a TorchScript encoder loaded from
    its file, else ``build_extractor``'s backbone and pooling head."""
    if config.backbone == TORCHSCRIPT:
        return load_encoder(str(config.weights), *config.normalization()).eval()
    if config.backbone == ONNX:  # the user's normalisation, else the file's own contract, else ImageNet's
        given = config.normalization() if config.mean is not None else None
        return load_onnx_encoder(str(config.weights), config.width, config.height, given, config.normalization())
    return build_extractor(config)


def build_extractor(config: ExtractorConfig) -> Extractor:
    """The backbone + pooling extractor a configuration describes, in eval mode (a NetVLAD head still needs
    ``init_netvlad``); a TorchScript encoder is ``build_encoder``'s."""
    if config.backbone in FILE_ENCODERS:
        raise SeqvprError(f"a {config.backbone} encoder has no backbone and pooling head (use build_encoder)")
    if config.backbone == "efficientnet-lite0":
        net = backbones.efficientnet_lite0(config.weights)
        mean, std = backbones.LITE_MEAN, backbones.LITE_STD
    else:
        net = backbones.resnet(int(config.backbone.removeprefix("resnet")), config.weights)
        mean, std = IMAGENET_MEAN, IMAGENET_STD
    pooling = GeM() if config.pooling == "gem" else NetVLAD(config.clusters, net.local_channels)
    return Extractor(net, pooling, mean, std).eval()


def init_netvlad(
    extractor: Extractor,
    paths: Sequence[Path],
    config: ExtractorConfig,
    *,
    device: str = "cpu",
    max_images: int = 300,
    per_image: int = 50,
    seed: int = 0,
    progress: Callable[[int], None] | None = None,
) -> None:
    """Initialise the NetVLAD head by k-means over local features of (up to ``max_images`` evenly spaced) images,
    ``per_image`` seeded random positions each, as the NetVLAD paper does."""
    if not isinstance(extractor.pooling, NetVLAD):
        raise SeqvprError("init_netvlad needs an extractor with a NetVLAD head (pooling 'netvlad')")
    chosen = [Path(paths[i]) for i in np.unique(np.linspace(0, len(paths) - 1, min(max_images, len(paths))).astype(int))]
    rng = torch.Generator().manual_seed(seed)
    samples = []
    extractor = extractor.to(device)
    with torch.no_grad():
        for begin in range(0, len(chosen), config.batch_size):
            batch = [load_image(p, config.width, config.height) for p in chosen[begin : begin + config.batch_size]]
            for images in _micro_batches(torch.stack(batch), device):
                local = extractor.feature_map(images).flatten(2).transpose(1, 2).cpu()  # [b, HW, C]
                for image_local in local:
                    pick = torch.randperm(len(image_local), generator=rng)[:per_image]
                    samples.append(image_local[pick])
            if progress:
                progress(len(batch))
    extractor.pooling.init_from_features(torch.cat(samples), seed=seed)


def _micro_batches(images: torch.Tensor, device: str) -> list[torch.Tensor]:
    """The batch on the device, split into CPU micro-batches in channels-last layout (faster there), whole on GPU."""
    images = images.to(device)
    if images.device.type != "cpu":
        return [images]
    images = images.contiguous(memory_format=torch.channels_last)
    return list(images.split(CPU_MICRO_BATCH))


def load_image(path: Path, width: int, height: int) -> torch.Tensor:
    """An RGB image resized to width x height as a [3, H, W] float tensor in [0, 1]; one-line error if unreadable."""
    rgb = read_image(path, "RGB").resize((width, height), Image.BILINEAR)
    return torch.from_numpy(np.asarray(rgb, dtype=np.float32) / 255.0).permute(2, 0, 1)


@dataclass(frozen=True)
class Extraction:
    """Descriptors of the readable images, which input rows they are, and the images skipped as unreadable."""

    descriptors: np.ndarray
    rows: np.ndarray
    skipped: tuple[Path, ...]
    cache_file: Path | None


def cache_key(config: ExtractorConfig, paths: Sequence[Path], head: str = "") -> str:
    """A digest of the configuration, the weights file's content, the pooling head's state (``head``, from
    ``model_digest``) and every image's path and content (so an image rewritten with its old size and mtime, as
    ``cp -p`` or ``rsync -t`` leave it, gets a new key); a TorchScript encoder's normalisation is in it as used."""
    # batching does not change rows; a built-in backbone's normalisation is part of the backbone
    settings = {k: v for k, v in asdict(config).items() if k not in ("batch_size", "mean", "std")}
    if config.backbone in FILE_ENCODERS:
        settings["normalization"] = config.normalization()
    digest = hashlib.sha256(json.dumps(settings, sort_keys=True).encode() + head.encode())
    for path in _weights_files(config) + list(paths):
        digest.update(f"{Path(path).resolve()}|{file_digest(path)}\n".encode())
    return digest.hexdigest()[:24]


def file_digest(path: str | Path) -> str:
    """A content digest of a file (BLAKE2b, read in 1 MiB blocks), or ``missing``."""
    try:
        with open(path, "rb") as handle:
            return hashlib.file_digest(handle, lambda: hashlib.blake2b(digest_size=16)).hexdigest()
    except OSError:
        return "missing"


def array_digest(*arrays: np.ndarray) -> str:
    """A digest of arrays' shapes, types and bytes: a cache entry's checksum."""
    digest = hashlib.blake2b(digest_size=16)
    for array in arrays:
        array = np.ascontiguousarray(array)
        digest.update(f"{array.dtype}{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def _weights_files(config: ExtractorConfig) -> list[Path]:
    """The weights file a configuration reads (none for random weights or ResNet without a checkpoint)."""
    if config.weights is None or (config.weights == "imagenet" and config.backbone != "efficientnet-lite0"):
        return []
    return [backbones.lite0_weights_path() if config.weights == "imagenet" else Path(config.weights)]


def extract_descriptors(
    paths: Sequence[Path],
    config: ExtractorConfig = ExtractorConfig(),
    *,
    device: str = "cpu",
    cache_dir: str | Path | None = None,
    skip_bad: bool = False,
    progress: Callable[[int], None] | None = None,
    extractor: nn.Module | None = None,
    engine: str = "auto",
) -> Extraction:
    """Descriptors [N, D] of the images, in batches; reused from ``cache_dir`` when nothing changed.

    ``extractor`` (optional) replaces the model built from ``config``; it must be what ``config`` describes, since
    the cache key is computed from ``config``. ``engine`` runs it (``features.engines``: torch, onnx or auto); the
    engines agree within ``engines.TOLERANCE``, so a cached entry serves either.
    """
    ensure_policy()  # the one thread policy (seqvpr.threads)
    paths = [Path(p) for p in paths]
    if not paths:
        raise SeqvprError("no images to extract descriptors from")
    if config.pooling == "netvlad" and extractor is None:
        raise SeqvprError("NetVLAD pooling needs an initialised extractor (build_extractor, then init_netvlad)")
    if cache_dir is not None:  # the cache writes beside no image: one check per folder of images
        check_output_apart(cache_dir, sorted({path.parent for path in paths}), "the descriptor cache")
    key = _extraction_key(config, paths, cache_dir, extractor)
    final = Path(cache_dir) / f"{key}.npz" if key else None
    cached = _load_cached(final, paths, progress)
    if cached is not None:
        return cached
    model = _prepare_model(config, extractor, device, engine)
    part = _Partial(Path(cache_dir) / f"{key}.part" if key else None)
    if progress and part.done:
        progress(part.done)
    _extract_remaining(model, paths, config, part, device=device, skip_bad=skip_bad, progress=progress)
    return _assemble(paths, part, final)


def _extraction_key(
    config: ExtractorConfig, paths: list[Path], cache_dir: str | Path | None, extractor: nn.Module | None
) -> str | None:
    """The cache key of this extraction (covering a NetVLAD head's state), or None when nothing is cached."""
    netvlad = extractor.pooling if isinstance(extractor, Extractor) and config.pooling == "netvlad" else None
    head = model_digest(netvlad) if netvlad is not None else ""
    return cache_key(config, paths, head) if cache_dir is not None else None


def _load_cached(final: Path | None, paths: list[Path], progress: Callable[[int], None] | None) -> Extraction | None:
    """The finished extraction stored in ``final``, reported as all done, or None when there is none to reuse. An
    entry that cannot be read or fails its checksum (a full disk, a killed writer) is deleted and recomputed."""
    if final is None or not final.is_file():
        return None
    arrays = _read_checked(final, ("descriptors", "rows", "skipped"))
    if arrays is None:
        return None
    if progress:
        progress(len(paths))
    return Extraction(arrays["descriptors"], arrays["rows"], tuple(paths[i] for i in arrays["skipped"]), final)


def _read_checked(file: Path, names: tuple[str, ...]) -> dict[str, np.ndarray] | None:
    """The named arrays of a cache file whose stored checksum matches them; else the file is removed, a one-line
    warning says so, and None is returned."""
    import warnings
    import zipfile

    from seqvpr.arrays import open_npz
    from seqvpr.errors import SeqvprWarning

    try:
        with open_npz(file) as saved:
            arrays = {name: saved[name] for name in (*names, "checksum")}
        if str(arrays.pop("checksum")) == array_digest(*(arrays[name] for name in names)):
            return arrays
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        pass
    warnings.warn(f"{file}: a damaged cache entry, removed; computing it again", SeqvprWarning, stacklevel=2)
    file.unlink(missing_ok=True)
    return None


def _prepare_model(config: ExtractorConfig, extractor: nn.Module | None, device: str, engine: str = "auto"):
    """The given (or newly built) model on the device, run by ``engine``; under torch a built-in backbone is
    channels-last on CPU (faster there), a TorchScript encoder as it was exported. ONNX Runtime describes a batch
    an image per thread of the policy (one-thread sessions side by side: faster on a CPU than one pool per image)."""
    model = with_engine((extractor or build_encoder(config)).to(device), config.width, config.height, engine, device)
    if isinstance(model, OnnxEncoder):
        return model.with_threads(1)
    if config.backbone != TORCHSCRIPT and str(device).startswith("cpu"):
        model = model.to(memory_format=torch.channels_last)
    return model


def _load_batch(
    paths: list[Path], begin: int, end: int, config: ExtractorConfig, skip_bad: bool,
    encode: Callable[[torch.Tensor], torch.Tensor] | None = None, pool: ThreadPoolExecutor | None = None,
) -> tuple[list[torch.Tensor], list[int], list[int]]:
    """Images ``begin..end-1`` as tensors, each passed through ``encode`` when given, on ``pool``'s threads side by
    side when given (PIL decodes and ONNX Runtime runs without the GIL), with the rows they are and the rows
    skipped as unreadable (if allowed)."""
    def read(index: int) -> torch.Tensor | SeqvprError:
        try:
            image = load_image(paths[index], config.width, config.height)
        except SeqvprError as error:
            return error
        return encode(image[None]) if encode else image

    loaded = list(pool.map(read, range(begin, end)) if pool else map(read, range(begin, end)))
    images: list[torch.Tensor] = []
    batch_rows: list[int] = []
    batch_skipped: list[int] = []
    for index, image in zip(range(begin, end), loaded):
        if isinstance(image, SeqvprError):
            if not skip_bad:
                raise image
            batch_skipped.append(index)
        else:
            images.append(image)
            batch_rows.append(index)
    return images, batch_rows, batch_skipped


def _extract_remaining(
    model: nn.Module,
    paths: list[Path],
    config: ExtractorConfig,
    part: _Partial,
    *,
    device: str,
    skip_bad: bool,
    progress: Callable[[int], None] | None,
) -> None:
    """Describe the batches after those ``part`` already holds, adding each to it (and its folder) as it finishes."""
    onnx = isinstance(model, OnnxEncoder)  # an image a call: read and described on one thread, one per core
    workers = torch.get_num_threads() if onnx else 1
    with torch.no_grad(), ThreadPoolExecutor(workers) as threads:
        pool = threads if workers > 1 else None
        for begin in range(part.done, len(paths), config.batch_size):
            end = min(begin + config.batch_size, len(paths))
            images, batch_rows, batch_skipped = _load_batch(paths, begin, end, config, skip_bad,
                                                            model if onnx else None, pool)
            if onnx:
                out = torch.cat(images).numpy() if images else None
            else:
                out = _describe_batch(model, images, device) if images else None
            if out is not None:
                part.rows.append(out)
            part.kept.extend(batch_rows)
            part.skipped.extend(batch_skipped)
            part.save_batch(begin, end, out, batch_rows, batch_skipped)
            if progress:
                progress(end - begin)


def _assemble(paths: list[Path], part: _Partial, final: Path | None) -> Extraction:
    """The extraction from all batches in ``part``, saved to the cache file ``final`` (if any) replacing the partial."""
    if not part.kept:
        raise SeqvprError(f"none of the {len(paths)} images could be read (first: {paths[part.skipped[0]]})")
    skipped = part.skipped
    result = Extraction(
        np.concatenate(part.rows), np.asarray(part.kept, np.int64), tuple(paths[i] for i in skipped), final
    )
    if final is not None:
        skipped_rows = np.asarray(skipped, np.int64)
        with atomic_write(final, "wb") as handle:
            np.savez(handle, descriptors=result.descriptors, rows=result.rows, skipped=skipped_rows,
                     checksum=array_digest(result.descriptors, result.rows, skipped_rows))
        part.remove()
    return result


def _describe_batch(model: nn.Module, images: list[torch.Tensor], device: str) -> np.ndarray:
    """Descriptors [n, D] of one batch of loaded images."""
    parts = [model(chunk).cpu() for chunk in _micro_batches(torch.stack(images), device)]
    return torch.cat(parts).numpy().astype(np.float32)


BATCH_ARRAYS = ("begin", "end", "descriptors", "kept", "skipped")


class _Partial:
    """Batches written so far by an interrupted extraction: one small .npz per finished batch in ``<key>.part/``."""

    def __init__(self, folder: Path | None) -> None:
        self.folder = folder
        self.done = 0
        self.rows: list[np.ndarray] = []
        self.kept: list[int] = []
        self.skipped: list[int] = []
        if folder is None or not folder.is_dir():
            return
        for file in sorted(folder.glob("batch_*.npz")):
            saved = _read_checked(file, BATCH_ARRAYS)
            if saved is None or int(saved["begin"]) != self.done:
                break  # only a contiguous run of sound batches from the start is reused
            if len(saved["kept"]):
                self.rows.append(saved["descriptors"])
            self.kept.extend(int(i) for i in saved["kept"])
            self.skipped.extend(int(i) for i in saved["skipped"])
            self.done = int(saved["end"])

    def save_batch(self, begin: int, end: int, descriptors: np.ndarray | None, kept: list[int], skipped: list[int]) -> None:
        if self.folder is None:
            return
        self.folder.mkdir(parents=True, exist_ok=True)
        arrays = {"begin": np.asarray(begin), "end": np.asarray(end),
                  "descriptors": descriptors if descriptors is not None else np.zeros((0, 0), np.float32),
                  "kept": np.asarray(kept, np.int64), "skipped": np.asarray(skipped, np.int64)}
        with atomic_write(self.folder / f"batch_{begin:09d}.npz", "wb") as handle:
            np.savez(handle, **arrays, checksum=array_digest(*(arrays[name] for name in BATCH_ARRAYS)))

    def remove(self) -> None:
        if self.folder is not None and self.folder.is_dir():
            shutil.rmtree(self.folder, ignore_errors=True)

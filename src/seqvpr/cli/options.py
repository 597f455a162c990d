"""Options and value parsers the command families share. Nothing here imports torch: ``--help`` and option errors
stay fast."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from seqvpr.errors import SeqvprError, os_refusal

#: how images become descriptors: patch-normalised thumbnails, one of the backbones, or torchscript:PATH
#: the one table from the library's setting names (what a Python caller passes, what its errors name) to the flags a
#: command-line user gives: an error naming ``{seq_len}`` reads ``--seq-len`` here (``SettingError.naming``)
FLAGS = {
    "seq_len": "--seq-len", "align": "--align", "boundary": "--boundary", "velocities": "--velocities",
    "method": "--method", "models": "--model", "model": "--model", "rerank": "--rerank", "index": "--index",
    "shortlist": "--shortlist", "history": "--shortlist-history", "nprobe": "--nprobe", "steps": "--steps",
    "contrast_window": "--contrast-window", "memory_budget": "--memory-budget",
    "dtype": "--dtype", "device": "--device", "normalize": "--no-normalize", "threshold": "--threshold",
    "lost_after": "--lost-after", "exclusion": "--exclusion", "keyframe_distance": "--keyframe-distance",
    "frames": "--frames", "radius": "--radius", "ground_truth": "--ground-truth", "uniqueness": "--uniqueness",
    "k": "--k", "overlap": "--overlap", "shards": "--shards", "pos_radius": "--pos-radius",
    "neg_radius": "--neg-radius", "negatives": "--negatives", "rate": "--rate", "cache_dir": "--cache-dir",
    "epochs": "--epochs", "target_precision": "--target-precision", "subtask": "--msls-subtask",
    "layout": "--gt-layout", "window_method": "--window-method", "windows": "--windows", "index_model": "--index-model",
    "topic": "--topic", "cell_size": "--cell-size", "resume": "--resume", "out": "--out", "weights": "--weights",
    "max_step": "--max-step", "image_size": "--image-size", "no_positive": "--no-positive", "optimizer": "--optimizer",
    "jitter": "--jitter", "hue": "--hue", "crop_scale": "--crop-scale", "max_iterations": "--max-iterations",
    "init": "--init", "trainable_stages": "--trainable-stages", "refresh_every": "--refresh-every",
    "batch_size": "--batch-size", "lr_step": "--lr-step", "lr": "--lr", "floor": "--floor", "engine": "--engine",
    "exclude": "--exclude", "shortlist_index": "--shortlist-index", "thumbnails": "--thumbnails",
}

BACKBONES = ("efficientnet-lite0", "resnet18", "resnet50")
DESCRIPTORS = ("patchnorm", *BACKBONES)
TORCHSCRIPT_PREFIX = "torchscript:"
ENCODER_PREFIXES = (TORCHSCRIPT_PREFIX, "onnx:")  # a user's own encoder file
POOLINGS = ("gem", "netvlad")


class WritablePath(click.ParamType):
    """A path seqvpr will write (a ``folder`` or a ``file``), checked when the options are parsed, before any work:
    an existing file where a folder goes, a path under a file, or a place nothing can be written is one line."""

    name = "path"

    def __init__(self, kind: str = "folder") -> None:
        self.kind = kind

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> str:
        if not str(value).strip():
            self.fail("an empty path; name the output", param, ctx)
        try:
            problem = output_problem(Path(value), self.kind)
        except OSError as error:  # the system refused even to look (a path too long, a loop): its one line
            refusal = os_refusal(error)
            if refusal is None:
                raise
            problem = str(refusal)
        if problem:
            self.fail(problem, param, ctx)
        return str(value)


def output_problem(path: Path, kind: str) -> str | None:
    """Why ``path`` cannot be written as a ``kind`` (``folder`` or ``file``), or None."""
    import errno
    import os
    import tempfile

    from seqvpr.io import NAME_MAX, is_set_link

    if any(len(os.fsencode(part)) > NAME_MAX for part in path.parts):  # before the lock or any temporary is made
        return str(os_refusal(OSError(errno.ENAMETOOLONG, os.strerror(errno.ENAMETOOLONG), str(path))))
    if path.is_symlink() and not path.exists() and not is_set_link(path):  # a set's name it lacks is no fault
        return f"{path} is a symbolic link to nothing (dangling, or a loop)"
    if path.exists() and (path.is_dir() != (kind == "folder")):
        return f"{path} is {'a folder' if path.is_dir() else 'not a folder'}, and a {kind} goes there"
    target = path if path.is_dir() else path.parent
    while not target.exists() and target != target.parent:
        target = target.parent
    if not target.is_dir():
        return f"{path} lies under {target}, which is not a folder"
    try:
        Path(tempfile.mkdtemp(prefix=".seqvpr-probe-", dir=target)).rmdir()
    except OSError as error:
        return f"{path}: nothing can be written in {target} ({error.strerror})"
    return None


OUT_FOLDER, OUT_FILE = WritablePath("folder"), WritablePath("file")


def locks_output(option: str) -> Callable[[Callable], Callable]:
    """Run a command holding ``seqvpr.io.output_lock`` on the output its ``option`` names (applied below the
    click decorators): two runs writing one ``--out`` never interleave."""
    import functools

    def decorate(function: Callable) -> Callable:
        @functools.wraps(function)
        def locked(*args: Any, **kwargs: Any) -> Any:
            target = kwargs.get(option)
            if not target or _torchrun_rank() != 0:  # under torchrun rank 0 alone writes the output
                return function(*args, **kwargs)
            from seqvpr.io import output_lock

            with output_lock(target):
                return function(*args, **kwargs)

        return locked

    return decorate


def _torchrun_rank() -> int:
    """This process's rank under torchrun (0 alone); a malformed value is left to ``seqvpr.distributed``."""
    import os

    try:
        return int(os.environ.get("RANK", 0))
    except ValueError:
        return 0


class Number(click.ParamType):
    """An int or a finite float within [low, high] (``open_low``: above low), checked when options are parsed: a
    NaN, an infinity or a value out of range is one line naming the option."""

    def __init__(self, kind: type, low: float | None = None, high: float | None = None, open_low: bool = False):
        self.kind, self.low, self.high, self.open_low = kind, low, high, open_low
        self.name = "integer" if kind is int else "number"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        import math

        from seqvpr.checks import in_range, range_text

        try:
            number = self.kind(value)
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a{'n integer' if self.kind is int else ' number'}", param, ctx)
        if self.kind is float and not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number", param, ctx)
        if not in_range(number, self.low, self.high, self.open_low):
            self.fail(f"{value} is not in {range_text(self.low, self.high, self.open_low)}", param, ctx)
        return number


class Device(click.ParamType):
    """A torch device this machine can use (``cpu``, ``cuda``, ``cuda:1``, ``mps``), checked when options are parsed,
    before any work: torch is imported only for a device other than ``cpu``."""

    name = "device"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> str:
        from seqvpr.checks import device

        try:
            return device(value, "device")
        except SeqvprError as error:  # the library's one check; click names the option itself
            self.fail(str(error).removeprefix("device "), param, ctx)


DEVICE = Device()
COUNT, NONNEGATIVE, SEED = Number(int, 1), Number(int, 0), Number(int, 0, 2**32 - 1)
POSITIVE, NONNEGATIVE_FLOAT, FINITE = Number(float, 0, open_low=True), Number(float, 0), Number(float)
FRACTION = Number(float, 0, 1, open_low=True)  # (0, 1]


def bag_topic_options(*sources: str) -> Callable[[Callable], Callable]:
    """``--topic``, ``--gps-topic``, ``--odom-topic`` and ``--stamp-tolerance`` for the ROS bags among the command's
    ``sources`` options: each bag source is rewritten to name them (a topic in the source itself, ``BAG:/topic``,
    is kept), so the library, run.json and a re-run see one source text. Given with no bag source, they are an error."""
    import functools

    def decorate(function: Callable) -> Callable:
        @functools.wraps(function)
        def rewritten(*args: Any, **kwargs: Any) -> Any:
            given = {k: kwargs.pop(k) for k in ("topic", "gps_topic", "odom_topic", "stamp_tolerance")}
            _apply_bag_topics(kwargs, sources, given)
            return function(*args, **kwargs)

        return with_options(BAG_OPTIONS)(rewritten)

    return decorate


BAG_OPTIONS = [
    click.option("--topic", help="ROS bag sources: the image topic (sensor_msgs/Image or CompressedImage)  "
                                 "[default: the bag's only image topic]."),
    click.option("--gps-topic", help="ROS bag sources: the NavSatFix topic giving positions (to UTM metres)  "
                                     "[default: the bag's NavSatFix topic, else its Odometry topic]."),
    click.option("--odom-topic", help="ROS bag sources: the nav_msgs/Odometry topic giving positions (x, y metres)."),
    click.option("--stamp-tolerance", type=POSITIVE, help="ROS bag sources: most seconds between a frame and its "
                                                       "position fix (frames without one are left out)  [default: 0.5]."),
]


def _apply_bag_topics(kwargs: dict[str, Any], sources: tuple[str, ...], given: dict[str, Any]) -> None:
    """Rewrite the bag sources among ``kwargs[sources]`` (a text or a tuple of texts) to carry the ``given`` topics."""
    if all(v is None for v in given.values()):
        return
    from dataclasses import replace

    from seqvpr.data.loaders.rosbag import bag_source, parse_bag_source

    def rewrite(text: str) -> str:
        bag = parse_bag_source(text)
        if bag is None:
            return text
        path, topics = bag
        named = {"image": topics.image or given["topic"], "gps": given["gps_topic"] or topics.gps,
                 "odom": given["odom_topic"] or topics.odom}
        if given["stamp_tolerance"] is not None:
            named["tolerance"] = given["stamp_tolerance"]
        bags.append(text)
        out = bag_source(path, replace(topics, **named))
        parse_bag_source(out)  # both position topics, or a bad tolerance, fail here, before any work
        return out

    bags: list[str] = []
    for name in sources:
        value = kwargs.get(name)
        if value:
            kwargs[name] = tuple(rewrite(v) for v in value) if isinstance(value, tuple) else rewrite(value)
    if not bags:
        flags = ", ".join("--" + k.replace("_", "-") for k, v in given.items() if v is not None)
        raise SeqvprError(f"{flags}: for ROS bag sources, and no source here is a bag")


def with_options(options: list[Callable]) -> Callable[[Callable], Callable]:
    """A decorator adding click ``options`` to a command, in the order ``--help`` shows them."""

    def decorate(function: Callable) -> Callable:
        for option in reversed(options):
            function = option(function)
        return function

    return decorate


def parse_ks(text: str) -> tuple[int, ...]:
    """``1,5,10,20`` -> (1, 5, 10, 20)."""
    message = f"--k {text!r}: expected comma-separated positive integers, e.g. 1,5,10,20"
    try:
        ks = tuple(sorted({int(x) for x in text.split(",") if x.strip()}))
    except ValueError:
        raise SeqvprError(message) from None
    if not ks or ks[0] < 1:
        raise SeqvprError(message)
    return ks


MIN_BUDGET, MAX_BUDGET = 1024, 1024**5  # --memory-budget bounds: 1K (a few rows) to 1P (past any machine)


def parse_size(text: str | None, option: str = "--memory-budget") -> int | None:
    """``512M``, ``2G`` or plain bytes -> bytes, from 1K to 1P; ``none`` -> no budget. NaN, infinities, zero,
    negative and absurd sizes are one line naming the option."""
    if text is None or text.lower() == "none":
        return None
    units = {"k": 1024, "m": 1024**2, "g": 1024**3, "t": 1024**4, "p": 1024**5}
    message = f"{option} {text!r}: expected bytes from 1K to 1P such as 512M or 2G, or none"
    try:
        scale = units.get(text[-1].lower(), 1)
        size = float(text[:-1] if text[-1].lower() in units else text) * scale
    except (ValueError, IndexError):
        raise SeqvprError(message) from None
    if not MIN_BUDGET <= size <= MAX_BUDGET:  # False for NaN
        raise SeqvprError(message)
    return int(size)


def parse_thumbnail(text: str, option: str = "--thumbnail") -> tuple[int, int]:
    """``WIDTHxHEIGHT`` -> (width, height), both positive and at most 8192."""
    try:
        width, height = (int(x) for x in text.lower().split("x"))
        if not (1 <= width <= 8192 and 1 <= height <= 8192):
            raise ValueError
        return width, height
    except ValueError:
        raise SeqvprError(f"{option} {text!r}: expected WIDTHxHEIGHT, each 1 to 8192, e.g. 64x32") from None


def parse_descriptor(text: str) -> str:
    """A --descriptor value: a known name, or ``torchscript:PATH`` naming an existing file."""
    if text in DESCRIPTORS:
        return text
    prefix = next((p for p in ENCODER_PREFIXES if text.startswith(p)), None)
    if prefix is None:
        raise SeqvprError(f"--descriptor {text!r}: choose from {', '.join(DESCRIPTORS)}, {TORCHSCRIPT_PREFIX}PATH or "
                          "onnx:PATH")
    path = Path(text.removeprefix(prefix))
    if not path.is_file():
        raise SeqvprError(f"--descriptor {text!r}: {path}: no such model file")
    return text


def parse_normalize(text: str) -> tuple[tuple[float, ...] | None, tuple[float, ...] | None]:
    """``imagenet`` (None, None: the extractor's default), ``none`` (pixels in [0, 1] as they are) or
    ``R,G,B/R,G,B`` -> (mean, std) of a TorchScript encoder's input, three values each, std positive."""
    if text.lower() == "imagenet":
        return None, None
    if text.lower() == "none":
        return (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
    try:
        mean, std = (tuple(float(x) for x in part.split(",")) for part in text.split("/"))
        if len(mean) != 3 or len(std) != 3 or min(std) <= 0:
            raise ValueError
        return mean, std
    except ValueError:
        raise SeqvprError(f"--normalize {text!r}: expected imagenet, none or MEAN/STD as R,G,B/R,G,B "
                          "(e.g. 0.5,0.5,0.5/0.5,0.5,0.5), std positive") from None


def parse_stages(text: str | None) -> tuple[str, ...] | None:
    """``stage7,head`` -> ('stage7', 'head'); nothing -> None (the backbone's default)."""
    stages = tuple(s.strip() for s in (text or "").split(",") if s.strip())
    return stages or None


#: how an image encoder runs (seqvpr.features.engines)
ENGINE_HELP = ("How a network describes images: onnx (ONNX Runtime's CPU engine over the network exported once and "
               "checked against torch; about half torch's time a frame), torch, or auto: onnx on the CPU where it "
               "exports, else torch.")
#: seqvpr.checks.ENGINES, spelled here so that --help imports nothing more (a test holds them equal)
ENGINES = ("auto", "torch", "onnx")
ENGINE_CHOICE = click.Choice(list(ENGINES))
ENGINE_OPTION = click.option("--engine", type=ENGINE_CHOICE, default="auto",
                             show_default=True, help=ENGINE_HELP)

extraction_options = with_options([
    click.option("--descriptor", default="patchnorm", show_default=True, metavar="NAME|torchscript:PATH|onnx:PATH",
                 callback=lambda _ctx, _param, value: parse_descriptor(value),
                 help=f"How images become descriptors: {', '.join(DESCRIPTORS)}, or your own encoder: "
                      "torchscript:PATH (a TorchScript or torch.export file) or onnx:PATH (an ONNX file; its input "
                      "size is read from it when fixed): normalised [B,3,H,W] images -> [B,D] descriptors, used as "
                      "returned. Descriptor files are used as they are."),
    click.option("--thumbnail", default="64x32", show_default=True, help="patchnorm: grayscale thumbnail WIDTHxHEIGHT."),
    click.option("--patch", default=8, show_default=True, type=COUNT, help="patchnorm: patch side in pixels."),
    click.option("--weights", default="imagenet", show_default=True,
                 help="Backbone weights: 'imagenet' (EfficientNet-Lite0's packaged weights) or a checkpoint path."),
    click.option("--pooling", type=click.Choice(list(POOLINGS)), default="gem", show_default=True,
                 help="Backbone pooling: GeM, or NetVLAD with clusters from k-means of local features."),
    click.option("--clusters", default=64, show_default=True, type=COUNT, help="netvlad: number of clusters."),
    click.option("--image-size", default="320x240", show_default=True,
                 help="Backbone or encoder file input WIDTHxHEIGHT (images are resized to it)."),
    click.option("--normalize", default="imagenet", show_default=True,
                 help="torchscript/onnx: input normalisation: imagenet (its mean and std; a seqvpr export's "
                      "own: pixels in [0, 1]), none (pixels in [0, 1]) or MEAN/STD as R,G,B/R,G,B."),
    click.option("--batch-size", "extract_batch", default=32, show_default=True, type=COUNT,
                 help="Images per backbone batch."),
    ENGINE_OPTION,
    click.option("--cache-dir", type=OUT_FOLDER, help="Cache extracted descriptors here (keyed by model and images)."),
    click.option("--skip-bad", is_flag=True, help="Skip unreadable images (listed on stderr) instead of failing."),
])


def extraction_settings(options: dict[str, Any], device: str = "cpu") -> tuple[str, Any, dict[str, Any]]:
    """The parsed extraction options: descriptor name, patchnorm config, keyword arguments of ``describe``."""
    width, height = parse_thumbnail(options["thumbnail"])
    image_width, image_height = parse_thumbnail(options["image_size"], "--image-size")
    from seqvpr.features.extraction import ExtractorConfig
    from seqvpr.features.patchnorm import PatchNormConfig

    descriptor = options["descriptor"]
    backbone, weights, mean, std = _encoder(descriptor, options["weights"], options["normalize"])
    if backbone == "onnx":
        image_width, image_height = _onnx_size(weights, (image_width, image_height))
    config = ExtractorConfig(backbone, weights, options["pooling"], image_width, image_height, options["extract_batch"],
                             options["clusters"], mean, std)
    return descriptor, PatchNormConfig(width, height, options["patch"]), {
        "extractor": config, "device": device, "cache_dir": options["cache_dir"], "skip_bad": options["skip_bad"],
        "engine": options["engine"],
    }


def _encoder(descriptor: str, weights: str, normalize: str) -> tuple[str, str, Any, Any]:
    """Backbone, weights, mean and std of the extractor: a TorchScript file with --normalize's mean and std, or a
    built-in backbone with --weights (and its own normalisation)."""
    for prefix in ENCODER_PREFIXES:
        if descriptor.startswith(prefix):
            if weights != "imagenet":
                raise SeqvprError(f"--weights does not apply to {prefix}PATH (the model file holds its weights)")
            return prefix.rstrip(":"), descriptor.removeprefix(prefix), *parse_normalize(normalize)
    if normalize.lower() != "imagenet":
        raise SeqvprError(f"--normalize applies to {TORCHSCRIPT_PREFIX}PATH and onnx:PATH only ({descriptor} "
                          "normalises as it was trained)")
    return (descriptor if descriptor != "patchnorm" else "efficientnet-lite0"), weights, None, None


def _onnx_size(path: str, given: tuple[int, int]) -> tuple[int, int]:
    """An ONNX encoder's input size: the one its file fixes when --image-size is left at its default (a file whose
    size is free needs --image-size), else the one given."""
    from seqvpr.features.engines import input_size

    if click.get_current_context().get_parameter_source("image_size") not in (click.core.ParameterSource.DEFAULT,
                                                                              None):
        return given
    fixed = input_size(path)
    if fixed is None:
        raise SeqvprError(f"--descriptor onnx:{path}: the model's input size is not fixed; give --image-size WxH")
    return fixed


EXTRACTION_KEYS = ("descriptor", "thumbnail", "patch", "weights", "pooling", "clusters", "image_size", "normalize",
                   "extract_batch", "cache_dir", "skip_bad", "engine")


def given_image_size(options: dict[str, Any]) -> tuple[int, int] | None:
    """--image-size when given on the command line (it overrides a model's own image size), else None."""
    from click.core import ParameterSource

    source = click.get_current_context().get_parameter_source("image_size")
    if source in (ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP, None):
        return None
    return parse_thumbnail(options["image_size"], "--image-size")


def frame_description(options: dict[str, Any], device: str):
    """The FrameDescription of the extraction options, and describe()'s remaining keyword arguments."""
    from seqvpr.maps import FrameDescription

    descriptor, patchnorm, extraction = extraction_settings(options, device)
    extractor = extraction.pop("extractor")
    extraction.pop("device")
    source = click.get_current_context().get_parameter_source("image_size")
    size = None if source in (click.core.ParameterSource.DEFAULT, None) else parse_thumbnail(options["image_size"])
    return FrameDescription(descriptor, patchnorm, extractor, size), extraction

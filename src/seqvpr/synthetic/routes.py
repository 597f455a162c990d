"""A small generated route for the demo and tests: reference and query descriptor traversals with positions.

Appearance along the route is a smooth random field (places a few metres apart look alike, distant ones do
not), with one stretch repeated elsewhere (perceptual aliasing). The query drives the route at another speed
profile (with a stop), a lateral offset, and under another condition: a fixed linear change of appearance plus
strong per-frame noise, so single frames are ambiguous and sequences are not. Deterministic for a seed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from seqvpr.data.sources import save_traversal_npz
from seqvpr.data.traversal import Traversal


def smooth_field(rng: np.random.Generator, length_m: float, dim: int, correlation_m: float, step_m: float = 0.5) -> np.ndarray:
    """Appearance samples every ``step_m`` metres: Gaussian noise low-pass filtered over ``correlation_m``."""
    n = int(length_m / step_m) + 1
    noise = rng.normal(size=(n, dim))
    width = max(1, int(correlation_m / step_m))
    kernel = np.exp(-0.5 * (np.arange(-3 * width, 3 * width + 1) / width) ** 2)
    field = np.stack([np.convolve(noise[:, c], kernel, mode="same") for c in range(dim)], axis=1)
    return field / field.std()


def route_xy(arc: np.ndarray, lateral: float = 0.0) -> np.ndarray:
    """Positions (metres) along a gently winding route at the given arc lengths, shifted sideways by ``lateral``."""
    x = arc
    y = 40.0 * np.sin(arc / 120.0)
    dy = (40.0 / 120.0) * np.cos(arc / 120.0)
    normal = np.stack([-dy, np.ones_like(dy)], axis=1) / np.sqrt(1 + dy**2)[:, None]
    return np.stack([x, y], axis=1) + lateral * normal


def speed_profile(rng: np.random.Generator, n: int, mean_step: float) -> np.ndarray:
    """Arc lengths of n frames with a varying speed (0.6x to 1.4x) and one stop."""
    speed = 1.0 + 0.4 * np.sin(np.linspace(0, 6 * np.pi, n) + rng.uniform(0, np.pi))
    stop = rng.integers(n // 4, n // 2)
    speed[stop : stop + 15] = 0.02
    return np.concatenate([[0.0], np.cumsum(speed[:-1])]) * mean_step


def generate_route(n_frames: int = 1500, dim: int = 128, seed: int = 0) -> tuple[Traversal, Traversal]:
    """Reference (2 m spacing) and query traversals of the same route under different conditions."""
    rng = np.random.default_rng(seed)
    step = 2.0
    length = n_frames * step * 1.1
    field = smooth_field(rng, length, dim, correlation_m=6.0)
    alias = len(field) // 5
    field[3 * alias : 3 * alias + alias // 3] = field[alias : alias + alias // 3]
    sample = lambda arc: field[np.clip((arc / 0.5).astype(int), 0, len(field) - 1)]  # noqa: E731

    ref_arc = np.arange(n_frames) * step
    reference = Traversal.from_descriptors(
        (sample(ref_arc) + 0.3 * rng.normal(size=(n_frames, dim))).astype(np.float32),
        name="reference", positions=route_xy(ref_arc), timestamps=ref_arc / 10.0,
    )
    qry_arc = np.minimum(speed_profile(rng, n_frames, step), ref_arc[-1])
    condition = np.eye(dim) + 0.5 * rng.normal(size=(dim, dim)) / np.sqrt(dim)
    query = Traversal.from_descriptors(
        (sample(qry_arc) @ condition + 3.0 * rng.normal(size=(n_frames, dim))).astype(np.float32),
        name="query", positions=route_xy(qry_arc, lateral=1.5), timestamps=np.arange(n_frames) / 5.0,
    )
    return reference, query


def write_demo_route(out: Path, n_frames: int = 1500, seed: int = 0) -> tuple[Path, Path]:
    """Generate the route and write ``reference.npz`` and ``query.npz`` traversal files into ``out``."""
    reference, query = generate_route(n_frames, seed=seed)
    ref_path, qry_path = out / "reference.npz", out / "query.npz"
    save_traversal_npz(ref_path, reference)
    save_traversal_npz(qry_path, query)
    return ref_path, qry_path

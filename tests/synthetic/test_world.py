"""The rendered synthetic world: determinism, poses (stops, lateral offset), route layout (train/test apart, a loop),
aliasing, every condition, and the image-folder output the project's loader reads."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seqvpr.data.loaders.image_folder import load_image_folder
from seqvpr.synthetic.world import (
    CONDITIONS,
    DRIVE_LANE,
    Drive,
    build_world,
    drive_poses,
    render_frame,
    render_traversal,
    route,
    write_demo_world,
)
from tests.helpers import examples

SMALL = (64, 48)


@pytest.fixture(scope="module")
def world():
    return build_world(0)


@pytest.fixture(scope="module")
def test_route(world):
    return route(world, "test")


def _distance_to_polyline(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """Distance of each point to the nearest segment of a polyline."""
    a, b = polyline[:-1], polyline[1:]
    ab = b - a
    t = np.clip(((points[:, None] - a[None]) * ab[None]).sum(-1) / np.maximum((ab**2).sum(-1), 1e-12), 0, 1)
    closest = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(points[:, None] - closest, axis=2).min(axis=1)


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_same_seed_gives_byte_identical_files_and_another_seed_other_images(tmp_path, world, test_route):
    drive = Drive(condition="rain", speed_variation=0.4, stops=1, seed=3)
    first = render_traversal(world, test_route, drive, 10, tmp_path / "a", *SMALL)
    second = render_traversal(world, test_route, drive, 10, tmp_path / "b", *SMALL)
    assert _files(first) == _files(second)
    assert len(_files(first)) == 11  # ten images and positions.csv
    other = build_world(1)
    third = render_traversal(other, route(other, "test"), drive, 10, tmp_path / "c", *SMALL)
    images = [name for name in _files(first) if name.endswith(".jpg")]
    assert all(_files(first)[name] != _files(third)[name] for name in images)
    assert not np.allclose(other.xs, world.xs)


def test_positions_csv_loads_with_the_project_loader_and_follows_the_route(tmp_path, world, test_route):
    drive = Drive(condition="day", speed_variation=0.4, stops=1, seed=5)
    folder = render_traversal(world, test_route, drive, 40, tmp_path / "drive", *SMALL)
    traversal = load_image_folder(folder, folder / "positions.csv")
    assert len(traversal) == 40
    assert traversal.image_paths[0].name == "000000.jpg"
    assert traversal.positions.shape == (40, 2) and traversal.headings.shape == (40,)
    assert np.all(np.diff(traversal.timestamps) > 0)
    assert np.all(traversal.segment_ids == 0)
    assert _distance_to_polyline(traversal.positions, test_route).max() < 0.01
    poses = drive_poses(test_route, drive, 40)
    np.testing.assert_allclose(traversal.positions, poses.positions, atol=2e-3)


def test_stops_repeat_positions_while_frames_and_time_advance(test_route):
    drive = Drive(speed_variation=0.4, stops=2, seed=7)
    poses = drive_poses(test_route, drive, 300)
    steps = np.linalg.norm(np.diff(poses.positions, axis=0), axis=1)
    standing = steps == 0.0
    assert standing.sum() >= 2 * 10  # two stops of 3-5 s at 4 fps
    runs = np.diff(np.concatenate([[0], standing.astype(int), [0]]))
    assert (runs == 1).sum() == 2  # exactly two separate stops
    assert np.all(np.diff(poses.timestamps) > 0)
    # the varying-speed drive covers the same distance as a constant-speed one
    constant = drive_poses(test_route, Drive(), 300)
    assert poses.arc[-1] == pytest.approx(constant.arc[-1])
    assert np.ptp(steps[~standing]) > 1.0  # speed really varies


@settings(max_examples=examples(25), deadline=None)
@given(
    variation=st.floats(0.0, 0.9),
    stops=st.integers(0, 3),
    seed=st.integers(0, 2**31),
    n=st.integers(1, 400),
    speed=st.floats(1.0, 20.0),
)
def test_any_drive_moves_forward_only_and_covers_a_constant_speed_drive_distance(variation, stops, seed, n, speed):
    route_xy = route(build_world(0), "test")
    drive = Drive(mean_speed=speed, speed_variation=variation, stops=stops, seed=seed)
    poses = drive_poses(route_xy, drive, n)
    assert poses.positions.shape == (n, 2) and np.isfinite(poses.positions).all()
    assert np.all(np.diff(poses.arc) >= 0)
    assert poses.arc[-1] == pytest.approx((n - 1) * speed / drive.fps)
    assert np.all((poses.headings >= 0) & (poses.headings < 360))


def test_bad_parameters_are_refused(world):
    with pytest.raises(ValueError, match="condition"):
        Drive(condition="snowstorm")
    with pytest.raises(ValueError, match="route"):
        route(world, "validation")
    with pytest.raises(ValueError, match="condition"):
        render_frame(world, (0.0, 0.0), 0.0, "snowstorm", *SMALL, np.random.default_rng(0))


def test_lateral_offset_moves_the_camera_sideways_to_the_left(test_route):
    centre = drive_poses(test_route, Drive(), 200)
    shifted = drive_poses(test_route, Drive(lateral_offset=2.5), 200)
    heading = np.radians(centre.headings)
    forward = np.stack([np.sin(heading), np.cos(heading)], axis=1)
    offset = shifted.positions - centre.positions
    np.testing.assert_allclose(np.linalg.norm(offset, axis=1), 2.5, atol=1e-6)
    left = forward[:, 0] * offset[:, 1] - forward[:, 1] * offset[:, 0]  # cross(forward, offset) > 0: to the left
    np.testing.assert_allclose(left, 2.5, atol=1e-6)
    np.testing.assert_allclose(shifted.headings, centre.headings)
    # away from the junction the route crosses itself, the nearest route point is 2.5 m away
    distance = _distance_to_polyline(shifted.positions, test_route)
    assert np.mean(np.abs(distance - 2.5) < 0.05) > 0.9


def test_train_and_test_routes_are_far_apart(world):
    train, test = route(world, "train"), route(world, "test")
    dense = drive_poses(train, Drive(mean_speed=4.0, fps=1.0), 700).positions
    assert _distance_to_polyline(dense, test).min() > 50.0
    assert np.linalg.norm(train[0] - train[-1]) < 1e-9 and np.linalg.norm(test[0] - test[-1]) < 1e-9  # closed


def test_the_route_has_a_loop_driven_the_same_way_again(test_route):
    poses = drive_poses(test_route, Drive(), 600)  # 1200 m at 2 m per frame
    gap = np.abs(poses.arc[:, None] - poses.arc[None, :])
    near = np.linalg.norm(poses.positions[:, None] - poses.positions[None, :], axis=2) < 3.0
    turn = np.abs((poses.headings[:, None] - poses.headings[None, :] + 180.0) % 360.0 - 180.0)
    revisits = near & (gap > 200.0) & (turn < 20.0)
    assert revisits.sum() >= 2 * 10  # at least ~20 m of the route driven twice in the same direction


def test_aliased_places_look_alike_while_distinct_places_do_not(world, test_route):
    def view(position, direction) -> np.ndarray:
        heading = np.degrees(np.arctan2(direction[0], direction[1]))
        image = render_frame(world, position, heading, "day", *SMALL, np.random.default_rng(0))
        return image.astype(np.float32)

    motifs = world.motifs["test"]
    assert len(motifs) >= 3
    aliased = [view(start + 5.0 * d + DRIVE_LANE * np.array([d[1], -d[0]]), d) for start, d in motifs]
    poses = drive_poses(test_route, Drive(), 600)
    picks = np.arange(40, 600, 90)
    distinct = [view(poses.positions[i], _unit(poses.headings[i])) for i in picks]
    alike = max(np.abs(a - b).mean() for k, a in enumerate(aliased) for b in aliased[k + 1 :])
    apart = np.median([np.abs(a - b).mean() for k, a in enumerate(distinct) for b in distinct[k + 1 :]])
    assert alike < 0.6 * apart


def _unit(heading_deg: float) -> np.ndarray:
    h = np.radians(heading_deg)
    return np.array([np.sin(h), np.cos(h)])


@pytest.mark.parametrize("condition", CONDITIONS)
def test_every_condition_renders(world, test_route, condition):
    image = render_frame(world, test_route[0], 90.0, condition, *SMALL, np.random.default_rng(1))
    assert image.shape == (SMALL[1], SMALL[0], 3) and image.dtype == np.uint8
    assert image.std() > 5  # a scene, not a flat colour


def test_night_is_much_darker_than_day_and_frames_are_noisy(world, test_route):
    poses = drive_poses(test_route, Drive(), 20)
    day = [render_frame(world, p, h, "day", *SMALL, np.random.default_rng(i)) for i, (p, h) in
           enumerate(zip(poses.positions[::5], poses.headings[::5]))]
    night = [render_frame(world, p, h, "night", *SMALL, np.random.default_rng(i)) for i, (p, h) in
             enumerate(zip(poses.positions[::5], poses.headings[::5]))]
    assert np.mean(night) < 0.5 * np.mean(day)
    again = render_frame(world, poses.positions[0], poses.headings[0], "day", *SMALL, np.random.default_rng(99))
    assert not np.array_equal(again, day[0])  # sensor noise and exposure differ per frame
    assert np.abs(again.astype(int) - day[0]).mean() < 8


def test_rendering_replaces_an_existing_folder_atomically(tmp_path, world, test_route):
    out = tmp_path / "traversal"
    out.mkdir()
    (out / "positions.csv").write_text("an old rendering")
    (out / "stale.txt").write_text("old")
    render_traversal(world, test_route, Drive(), 3, out, *SMALL)
    assert sorted(p.name for p in out.iterdir()) == ["000000.jpg", "000001.jpg", "000002.jpg", "positions.csv"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["traversal"]  # no temporary or old folder left


def test_an_interrupted_render_leaves_no_folder_behind(tmp_path, world, test_route):
    def interrupt(done: int) -> None:
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        render_traversal(world, test_route, Drive(), 5, tmp_path / "traversal", *SMALL, progress=interrupt)
    assert list(tmp_path.iterdir()) == []


def test_demo_world_writes_four_traversals_and_reports_progress(tmp_path):
    ticks: dict[str, int] = {}

    def factory(total: int, label: str):
        ticks[label] = 0
        assert total == 6

        def tick(n: int) -> None:
            ticks[label] += n

        return tick

    paths = write_demo_world(tmp_path / "demo", frames=6, width=32, height=24, progress_factory=factory)
    assert set(paths) == {"train_reference", "train_query", "test_reference", "test_query"}
    assert sorted(ticks.values()) == [6, 6, 6, 6]
    query = load_image_folder(paths["test_query"], paths["test_query"] / "positions.csv")
    reference = load_image_folder(paths["test_reference"], paths["test_reference"] / "positions.csv")
    assert len(query) == len(reference) == 6
    offset = np.linalg.norm(query.positions[0] - reference.positions[0])
    assert 2.0 <= offset <= 3.0  # the query drives another lane

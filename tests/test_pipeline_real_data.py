"""The figures ../shared/data says a correct implementation reproduces, through the command line."""

import json
import sys

import numpy as np
import pytest

from seqvpr.cli import main

pytestmark = pytest.mark.slow  # whole real datasets: seconds each

GARDENS = "gardenspoint_delf_hdc/descriptors/GardensPointWalking/{}/delf_hdc_4096_ortho_sigma_nx5ny7.mat"


def recall(monkeypatch, capsys, tmp_path, *args):
    monkeypatch.setattr(sys, "argv", ["seqvpr", "match", *map(str, args), "--k", "1,5,20", "--json", "--out", tmp_path])
    main()
    result = json.loads(capsys.readouterr().out)
    return tuple(round(result["recall"][k], 3) for k in ("1", "5", "20"))


@pytest.mark.parametrize(
    "pair,length,expected",
    [
        (("day_left", "night_right"), 1, (0.670, 0.890, 0.970)),
        (("day_left", "night_right"), 5, (0.821, 0.980, 1.000)),
        (("day_left", "night_right"), 10, (0.937, 1.000, 1.000)),
        (("day_right", "night_right"), 3, (0.970, 1.000, 1.000)),
        (("day_right", "day_left"), 5, (0.939, 1.000, 1.000)),
    ],
)
def test_gardens_point(monkeypatch, capsys, tmp_path, shared_data, pair, length, expected):
    ref, qry = (shared_data / GARDENS.format(name) for name in pair)
    assert recall(monkeypatch, capsys, tmp_path, "-r", ref, "-q", qry, "--radius", "2f", "-L", length) == expected


@pytest.mark.parametrize("length,expected", [(1, (0.194, 0.342, 0.502)), (5, (0.584, 0.683, 0.770)), (20, (0.825, 0.855, 0.904))])
def test_nordland(monkeypatch, capsys, tmp_path, shared_data, length, expected):
    root = shared_data / "nordland_64x32"
    args = ["-r", root / "summer", "-q", root / "winter", "--frames", "17:2000", "--radius", "1f", "-L", length]
    assert recall(monkeypatch, capsys, tmp_path, *args) == expected


def test_gardens_point_gt_files_agree_with_frame_radius(monkeypatch, capsys, tmp_path, shared_data):
    ref, qry = (shared_data / GARDENS.format(name) for name in ("day_left", "night_right"))
    vprbench = shared_data / "gardenspoint_delf_hdc/vprbench_gt/ground_truth_new.npy"
    by_file = recall(monkeypatch, capsys, tmp_path, "-r", ref, "-q", qry, "--ground-truth", vprbench, "-L", 5)
    assert by_file == (0.821, 0.980, 1.000)
    gt_mat = shared_data / "gardenspoint_delf_hdc/ground_truth/GardensPointWalking/day_left--night_right/gt.mat"
    hard = recall(monkeypatch, capsys, tmp_path, "-r", ref, "-q", qry, "--ground-truth", gt_mat, "-L", 1)
    assert hard[0] <= 0.670  # GThard is exact-frame only, stricter than ±2 frames


def test_corridor_images_match(monkeypatch, capsys, tmp_path, shared_data):
    root = shared_data / "corridor"
    gt = root / "ground_truth_new.npy"
    single = recall(monkeypatch, capsys, tmp_path, "-r", root / "ref", "-q", root / "query", "--ground-truth", gt)
    sequence = recall(monkeypatch, capsys, tmp_path, "-r", root / "ref", "-q", root / "query", "--ground-truth", gt, "-L", 5)
    assert sequence[0] >= single[0] and single[0] > 0.3


@pytest.mark.parametrize("length,expected", [(1, (0.194, 0.342, 0.502)), (5, (0.584, 0.683, 0.770))])
def test_nordland_through_a_saved_map(monkeypatch, capsys, tmp_path, shared_data, length, expected):
    """``seqvpr map build`` of the summer images, then ``match --map`` with winter: the direct figures."""
    root = shared_data / "nordland_64x32"
    monkeypatch.setattr(sys, "argv", ["seqvpr", "map", "build", str(root / "summer"), "--frames", "17:2000",
                                      "--out", str(tmp_path / "map")])
    main()
    capsys.readouterr()
    args = ["--map", tmp_path / "map", "-q", root / "winter", "--frames", "17:2000", "--radius", "1f", "-L", length]
    assert recall(monkeypatch, capsys, tmp_path / "out", *args) == expected


def test_a_dense_ground_truth_matrix_gives_the_figures_of_its_gt_mat(monkeypatch, capsys, tmp_path, shared_data):
    """Gardens Point's GThard [n_reference, n_query] saved as a dense boolean .npy: the same figures as the .mat
    (square, so the layout must be given)."""
    import scipy.io

    ref, qry = (shared_data / GARDENS.format(name) for name in ("day_left", "night_right"))
    gt_mat = shared_data / "gardenspoint_delf_hdc/ground_truth/GardensPointWalking/day_left--night_right/gt.mat"
    hard = scipy.io.loadmat(gt_mat)["GT"]["GThard"][0, 0]
    np.save(tmp_path / "dense.npy", np.asarray(hard != 0))
    common = ("-r", ref, "-q", qry, "-L", 5)
    by_mat = recall(monkeypatch, capsys, tmp_path / "a", *common, "--ground-truth", gt_mat)
    by_dense = recall(monkeypatch, capsys, tmp_path / "b", *common, "--ground-truth", tmp_path / "dense.npy",
                      "--gt-layout", "ref-query")
    assert by_dense == by_mat

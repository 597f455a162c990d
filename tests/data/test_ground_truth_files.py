"""Ground-truth files: a dense boolean matrix in either layout equals the GT .mat of the same positives; its
orientation follows the traversal sizes, and a square one needs a layout."""

import numpy as np
import pytest
import scipy.io

from seqvpr.data.loaders.ground_truth_files import load_ground_truth_file
from tests.helpers import raises_one_line


@pytest.fixture
def positives():
    rng = np.random.default_rng(0)
    return rng.random((7, 5)) < 0.3  # [n_reference, n_query], as GT .mat and VPR-Bench store it


def dense(gt):
    return gt.positives.toarray()


def test_a_dense_matrix_equals_the_gt_mat_in_both_layouts(tmp_path, positives):
    scipy.io.savemat(tmp_path / "gt.mat", {"GT": {"GThard": positives.astype(np.uint8)}})
    np.save(tmp_path / "rq.npy", positives)
    np.savez(tmp_path / "qr.npz", gt=positives.T.astype(np.uint8))
    by_mat = dense(load_ground_truth_file(tmp_path / "gt.mat"))
    np.testing.assert_array_equal(dense(load_ground_truth_file(tmp_path / "rq.npy", 5, 7)), by_mat)
    np.testing.assert_array_equal(dense(load_ground_truth_file(tmp_path / "qr.npz", 5, 7)), by_mat)
    np.testing.assert_array_equal(dense(load_ground_truth_file(tmp_path / "rq.npy", 5, 6)), by_mat)  # a cut
    raises_one_line("both ways", load_ground_truth_file, tmp_path / "rq.npy", 3, 4)  # a cut that fits either way


def test_square_matrices_need_a_layout_and_bad_ones_are_one_line(tmp_path):
    square = np.eye(4, dtype=bool)
    square[0, 1] = True
    np.save(tmp_path / "sq.npy", square)
    raises_one_line("fits 4 reference and 4 query frames both ways: give layout", load_ground_truth_file,
                    tmp_path / "sq.npy", 4, 4)
    np.testing.assert_array_equal(dense(load_ground_truth_file(tmp_path / "sq.npy", 4, 4, "ref-query")), square.T)
    np.testing.assert_array_equal(dense(load_ground_truth_file(tmp_path / "sq.npy", 4, 4, "query-ref")), square)
    np.save(tmp_path / "small.npy", np.ones((2, 3), bool))
    raises_one_line("fits neither 4 reference x 5 query frames", load_ground_truth_file, tmp_path / "small.npy", 5, 4)
    np.save(tmp_path / "values.npy", np.full((4, 5), 2))
    raises_one_line("booleans or 0/1", load_ground_truth_file, tmp_path / "values.npy", 5, 4)

"""The public face: ``import seqvpr`` is light, and ``seqvpr.match`` takes a traversal, a map or a sharded map (or
their paths) and gives what each mode's own entry point gives; bad input is one line."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import seqvpr
from seqvpr.data.sources import save_traversal_npz
from seqvpr.errors import SeqvprError
from seqvpr.maps.sharding import shard_map
from seqvpr.matchers.sequence import SequenceMatcher
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.windows import SequenceSpec
from seqvpr.synthetic.routes import generate_route
from tests.helpers import raises_one_line


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("api")
    reference, query = generate_route(n_frames=160, dim=12, seed=2)
    save_traversal_npz(folder / "ref.npz", reference)
    save_traversal_npz(folder / "qry.npz", query)
    seqvpr.build_map([str(folder / "ref.npz")], folder / "map")
    shard_map(folder / "map", folder / "sharded", 3, 8)
    return folder


@pytest.mark.slow
def test_import_seqvpr_loads_no_heavy_library_and_names_the_public_face():
    code = "import sys, seqvpr; print(sorted(m for m in ('torch', 'numpy', 'faiss', 'numba') if m in sys.modules))"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True).stdout.strip() == "[]"
    assert {"match", "evaluate", "load_traversal", "build_map", "open_map", "Localizer"} <= set(dir(seqvpr))
    with pytest.raises(AttributeError):
        seqvpr.no_such_name  # noqa: B018


def test_match_takes_a_traversal_a_map_and_a_sharded_map_by_object_or_path(files):
    reference = seqvpr.load_traversal(str(files / "ref.npz"), "reference")
    query = seqvpr.load_traversal(str(files / "qry.npz"), "query")
    expected = SequenceMatcher(MatchSettings(SequenceSpec(5), k=7)).topk(reference, query).topk
    for given in (reference, files / "ref.npz", files / "map", seqvpr.open_map(files / "map"), files / "sharded",
                  seqvpr.open_map(files / "sharded")):
        found = seqvpr.match(given, files / "qry.npz", "matching", seq_len=5, k=7).topk
        np.testing.assert_array_equal(found.indices, expected.indices, err_msg=str(given))
        np.testing.assert_allclose(found.distances, expected.distances, rtol=1e-5)
    evaluation = seqvpr.evaluate(seqvpr.match(reference, query, seq_len=5), radius="5m")
    assert 0.0 < evaluation.recall[1] <= evaluation.recall[20] <= 1.0


@pytest.mark.parametrize("call, message", [
    (lambda f: seqvpr.match(f / "nope.npz", f / "qry.npz"), "nope.npz: no such file"),
    (lambda f: seqvpr.match(None, f / "qry.npz"), "the reference must be a traversal, a map or the path of one"),
    (lambda f: seqvpr.match(f / "ref.npz", np.zeros((3, 12))), "the query must be a traversal"),
    (lambda f: seqvpr.match(f / "ref.npz", f / "qry.npz", "magic"), "method 'magic' is not known"),
    (lambda f: seqvpr.match(f / "ref.npz", f / "qry.npz", seq_len=500), "longer than every segment"),
    (lambda f: seqvpr.match(f / "ref.npz", f / "qry.npz", shortlist=5), "needs a map with an index"),
    (lambda f: seqvpr.match(f / "ref.npz", f / "qry.npz", k=0), "k must be an integer in [1, inf], got 0"),
    (lambda f: seqvpr.match(f / "ref.npz", f / "qry.npz", kk=3), "no setting 'kk'"),
    (lambda f: seqvpr.match(f / "map", f / "qry.npz", normalize=False), "match it with normalisation on"),
])
def test_bad_input_to_match_is_one_line(files, call, message):
    raises_one_line(message, call, files)


def test_nan_in_a_query_is_one_line(files):
    with pytest.raises(SeqvprError, match="nan-query: descriptor row 0 contains NaN"):
        seqvpr.match(files / "ref.npz", seqvpr.Traversal.from_descriptors(np.full((20, 12), np.nan, np.float32),
                                                                         "nan-query"))

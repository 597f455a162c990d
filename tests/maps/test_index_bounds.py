"""An index spec is checked against its map before any training, and a shortlist is clipped to the index (the same
result) and checked against the memory budget (issue 28)."""

from __future__ import annotations

import pytest

from seqvpr.errors import SeqvprError
from seqvpr.maps.index import MAX_HNSW_M, PQ_CENTROIDS, check_index_spec, parse_index_spec
from seqvpr.matchers.shortlisted import shortlist_size
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.windows import SequenceSpec


@pytest.mark.parametrize("text, n, dim, fragment", [
    ("ivf:65536", 1000, 64, "65536 lists for 1000 frames"),
    ("ivf:16,pq:7", 1000, 64, "pq:7 must divide the dimension 64"),
    ("ivf:4,pq:8", PQ_CENTROIDS - 1, 64, f"needs at least {PQ_CENTROIDS} frames"),
])
def test_a_spec_too_large_for_its_map_is_one_line(text, n, dim, fragment):
    with pytest.raises(SeqvprError, match=fragment):
        check_index_spec(parse_index_spec(text), n, dim)


def test_a_spec_that_fits_passes():
    for text in ("flat", "hnsw:32", "ivf:1000", "ivf:4,pq:8"):
        check_index_spec(parse_index_spec(text), 1000, 64)
    check_index_spec(parse_index_spec("ivf:4,pq:8"), PQ_CENTROIDS, 64)


@pytest.mark.parametrize("text", ["hnsw:1", f"hnsw:{MAX_HNSW_M + 1}", "hnsw:100000000"])
def test_hnsw_links_are_bounded(text):
    with pytest.raises(SeqvprError, match=f"at least 2 and at most {MAX_HNSW_M}"):
        parse_index_spec(text)


def test_a_shortlist_is_clipped_to_the_index_and_the_history_to_the_query():
    settings = MatchSettings(SequenceSpec(5), memory_budget=None)
    assert shortlist_size(10**9, 10**9, vectors=300, n_query=40, settings=settings) == (300, 40)
    assert shortlist_size(20, 3, vectors=300, n_query=40, settings=settings) == (20, 3)


def test_a_shortlist_over_the_memory_budget_is_one_line():
    settings = MatchSettings(SequenceSpec(5), memory_budget=2**20)
    shortlist_size(10, 0, vectors=300, n_query=100, settings=settings)  # 100 x 5 x 10 x 24 bytes: within 1 MiB
    with pytest.raises(SeqvprError, match="shortlist 300 with history 0 and seq_len 5: .* over the "
                                          "memory_budget"):
        shortlist_size(300, 0, vectors=300, n_query=100, settings=settings)

"""Every size a user can ask for is checked against what it would cost before the work starts (issue 28): one line
on stderr naming the option and its limit, exit status 2, no partial output. One row a case, as in
``test_bad_inputs``; below the table, the sizes that are clipped instead give the result of the largest useful one."""

from __future__ import annotations

import json

import pytest

from tests.helpers import QuietCapsys, run_bad_case, run_cli, write_route_files


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """Traversals of 80 frames and a map of them with an IVF index."""
    w = write_route_files(tmp_path_factory.mktemp("bounds"), 80, 16, 2)
    monkeypatch = pytest.MonkeyPatch()
    code = run_cli(monkeypatch, QuietCapsys(), "map", "build", w / "ref.npz", "--index", "ivf:4", "--out", w / "map")[0]
    monkeypatch.undo()
    assert code == 0
    return w



M = ("match", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m", "--out", "{out}")
MAP = ("match", "--map", "{w}/map", "-q", "{w}/qry.npz", "--radius", "10m", "--out", "{out}")
TRAIN = ("train", "seqmatchnet", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m", "--train-frames",
         "0:50", "--val-frames", "50:80", "--epochs", "1", "--out", "{out}")
CASES = {
    # --- --velocities: counted before it is made
    "velocities: a tiny step (15 million trajectories)": ((*M, "--velocities", "0.5:2:1e-7"), "15000001 velocities, at most 1000"),
    "velocities: a tiny step, seqslam": ((*M, "--method", "seqslam", "--velocities", "0.5:2:1e-6"), "at most 1000"),
    "velocities: an absurd slope": ((*M, "--velocities", "1e300"), "must be in (0, 100]"),
    "velocities: NaN in a list": ((*M, "--velocities", "0.8,1,nan"), "got nan"),
    "velocities: an infinite range": ((*M, "--velocities", "0.5:inf:1"), "got inf"),
    # --- --memory-budget
    "memory budget: inf (was a traceback)": ((*M, "--memory-budget", "inf"), "--memory-budget 'inf'"),
    "memory budget: nan": ((*M, "--memory-budget", "nan"), "--memory-budget 'nan'"),
    "memory budget: negative": ((*M, "--memory-budget", "-1G"), "from 1K to 1P"),
    "memory budget: zero": ((*M, "--memory-budget", "0"), "from 1K to 1P"),
    "memory budget: absurdly small": ((*M, "--memory-budget", "10"), "from 1K to 1P"),
    "memory budget: absurdly large": ((*M, "--memory-budget", "5P"), "from 1K to 1P"),
    # --- -L
    "-L: 1e30": ((*M, "-L", "1e30"), "'-L': '1e30' is not an integer"),
    "-L: not an integer": ((*M, "-L", "2.5"), "'-L': '2.5' is not an integer"),
    "-L: zero": ((*M, "-L", "0"), "'-L': 0 is not in [1, inf]"),
    "-L: negative": ((*M, "-L", "-3"), "'-L': -3 is not in [1, inf]"),
    "-L: huge, names the longest segment": ((*M, "-L", "100000000000"), "--seq-len 100000000000: longer than every segment of reference"),
    "-L: huge against a map": ((*MAP, "-L", "100000"), "(longest segment:"),
    # --- --shortlist
    "shortlist: 1e9 is not an integer": ((*MAP, "--shortlist", "1e9"), "'--shortlist': '1e9' is not an integer"),
    "shortlist: candidates over the memory budget": ((*MAP, "--shortlist", "1000000000", "--shortlist-history", "1000000000", "--memory-budget", "1M"), "over the --memory-budget"),
    # --- --index specs too large for their map: one line before building
    "index: more IVF lists than frames": (("map", "index", "{w}/map", "--index", "ivf:65536"), "65536 lists for 80 frames"),
    "index: PQ not dividing the dimension": (("map", "index", "{w}/map", "--index", "ivf:4,pq:5"), "must divide the dimension 16"),
    "index: PQ with fewer frames than its k-means needs": (("map", "index", "{w}/map", "--index", "ivf:2,pq:4"), "needs at least 256 frames"),
    "index: hnsw:1 (was a segmentation fault)": (("map", "index", "{w}/map", "--index", "hnsw:1"), "hnsw:M needs M at least 2"),
    "index: hnsw with absurd links (was bad_alloc)": (("map", "index", "{w}/map", "--index", "hnsw:100000000"), "at most 256"),
    "map build: IVF lists past the frames, nothing left": (("map", "build", "{w}/ref.npz", "--index", "ivf:65536", "--out", "{out}"), "65536 lists for 80 frames"),
    # --- other sizes
    "localize: --max-step past the bound": (("localize", "--map", "{w}/map", "-q", "{w}/qry.npz", "--method", "hmm", "--max-step", "1000000000", "--out", "{out}"), "--max-step 1000000000 is above 1000"),
    "demo: a billion frames": (("demo", "--frames", "1000000000", "--out", "{out}"), "at most 20000"),
    "train: --out-dim of a billion (was a 64 GB allocation)": ((*TRAIN, "--out-dim", "1000000000"), "--out-dim 1000000000: at most 65536"),
    "train: --negatives of a billion (was a 1.5 TB allocation)": ((*TRAIN, "--negatives", "1000000000"), "--negatives must be from 1 to 1000"),
    "train seqnet: --out-dim of a billion": ((*TRAIN[:1], "seqnet", *TRAIN[2:], "--out-dim", "1000000000"), "at most 65536"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_size_past_its_bound_is_one_line_exit_2_and_no_partial_output(world, tmp_path, monkeypatch, capsys, case):
    args, fragment = CASES[case]
    out = tmp_path / "out"
    run_bad_case(monkeypatch, capsys, args, fragment, world, out)


def _predictions(monkeypatch, capsys, out, *args) -> str:
    code, _, err = run_cli(monkeypatch, capsys, *args, "--out", out)
    assert code == 0, err
    return (out / "predictions.csv").read_text()


def test_a_shortlist_past_the_map_is_clipped_to_it_with_the_same_result(world, tmp_path, monkeypatch, capsys):
    base = ("match", "--map", world / "map", "-q", world / "qry.npz", "--radius", "10m", "-L", "3")
    whole = _predictions(monkeypatch, capsys, tmp_path / "a", *base, "--shortlist", "80", "--shortlist-history", "80")
    huge = _predictions(monkeypatch, capsys, tmp_path / "b", *base, "--shortlist", "1000000000",
                        "--shortlist-history", "1000000000")
    assert huge == whole
    assert json.loads((tmp_path / "b" / "run.json").read_text())["recall"]


def test_a_k_past_the_reference_is_clipped_to_it(world, tmp_path, monkeypatch, capsys):
    base = ("match", "-r", world / "ref.npz", "-q", world / "qry.npz", "--radius", "10m", "-L", "3")
    code, out, err = run_cli(monkeypatch, capsys, *base, "--k", "1,1000000000", "--out", tmp_path / "k", "--json")
    assert code == 0, err
    widths = {len(row.split(",")[2].split()) for row in (tmp_path / "k" / "predictions.csv").read_text().splitlines()[1:]}
    assert max(widths) <= 80
    assert 0 <= json.loads(out)["recall"]["1000000000"] <= 1

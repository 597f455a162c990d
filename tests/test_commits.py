"""Multi-file outputs commit as one: every rename that commits an output (``seqvpr.io.rename`` / ``exchange``) is
made to fail in turn while a writer replaces its old output with a new one, and a writer is killed (SIGKILL) while
it writes; each time a reader finds exactly the old output or exactly the new, never a mix, and the next run leaves
no temporary behind."""

from __future__ import annotations

import csv
import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import seqvpr.io
from tests.helpers import run_cli, write_route_files

ROOT = Path(__file__).resolve().parents[1]


class Injected(OSError):
    """The failure a test injects into a commit rename."""


class FailOn:
    """``seqvpr.io.rename`` and ``exchange`` that count their calls, the ``k``-th raising ``Injected``."""

    def __init__(self, k: int) -> None:
        self.k, self.calls = k, 0
        self.real = (seqvpr.io.rename, seqvpr.io.exchange)

    def rename(self, source, target) -> None:
        self._count(source)
        self.real[0](source, target)

    def exchange(self, first, second) -> None:
        self._count(first)
        self.real[1](first, second)

    def _count(self, path) -> None:
        self.calls += 1
        if self.calls == self.k:
            raise Injected(errno.EIO, "injected failure", str(path))


# ---- the writers: an old run, a new run with other inputs, the output's visible state, a reader's check ----------

def _tables(out: str, generation: str) -> None:
    """The benchmark's results.csv / results.md pair, of rows whose figures say which ``generation`` wrote them."""
    from seqvpr.experiments.benchmark import BenchmarkConfig, DatasetSpec, Row
    from seqvpr.experiments.tables import write_results

    figure = {"old": 0.25, "new": 0.75}[generation]
    config = BenchmarkConfig((DatasetSpec("d", "r", "q", "1f", "0:1", "1:2", "2:3"),), ("matching",), 5, (5,), (1,))
    write_results([Row("d", "matching", 5, _evaluation(figure))], config, Path(out))


def _ablation(out: str, generation: str) -> None:
    """The ablation's ablation.csv / ablation.md pair, written beside a variant's run folder."""
    from seqvpr.experiments.ablation import AblationRow, write_ablation

    figure = {"old": 0.25, "new": 0.75}[generation]
    rows = [AblationRow("untransformed", None, None, _evaluation(figure), None),
            AblationRow("single/single", "single", "single", _evaluation(figure / 2), SimpleNamespace(best_epoch=3))]
    write_ablation(rows, (1,), out)


def _evaluation(recall: float) -> SimpleNamespace:
    """What the table writers read of an evaluation."""
    return SimpleNamespace(recall={1: recall}, queries_evaluated=10, frame_precision=float("nan"),
                           pr=SimpleNamespace(auc=recall / 2, recall_at_100_precision=0.0))


def _plain_tables(out: str) -> None:
    """results.csv / results.md as plain files, as seqvpr wrote them before pairs were committed as one."""
    import shutil

    scratch = Path(out).parent / "scratch"
    _tables(str(scratch), "old")
    for name in ("results.csv", "results.md"):
        shutil.copy(scratch / name, Path(out) / name)


FUNCTIONS = {"@tables": _tables, "@ablation": _ablation, "@plain": _plain_tables}


def _match_check(d: Path, capsys) -> None:
    """``seqvpr eval`` on the predictions gives run.json's recall; the correspondences have run.json's length."""
    out = d / "o"
    run = json.loads((out / "run.json").read_text())
    code, text, err = run_cli(pytest.MonkeyPatch(), capsys, "eval", out / "predictions.csv", "-r", d / "a" / "ref.npz",
                              "-q", d / "a" / "qry.npz", "--radius", "10m", "--json")
    assert code == 0, err
    assert json.loads(text)["recall"] == run["recall"]
    with open(out / "correspondences.csv", newline="") as handle:
        positions = {int(row["position"]) for row in csv.DictReader(handle)}
    assert max(positions) + 1 == run["settings"]["sequence"]["length"]


def _localize_check(d: Path, capsys) -> None:
    """stream.csv has run.json's frames and statuses; the report is there exactly when run.json has measures."""
    out = d / "lo"
    run = json.loads((out / "run.json").read_text())
    with open(out / "stream.csv", newline="") as handle:
        statuses = [row["status"] for row in csv.DictReader(handle)]
    assert len(statuses) == run["frames"]
    assert {s: statuses.count(s) for s in run["status"]} == run["status"]
    assert (out / "report" / "index.html").is_file() == ("recall" in run)


def _convert_check(d: Path, capsys) -> None:
    """The dataset.toml reads back as traversals of the .db's sizes, and a descriptors file is there exactly when
    the toml names it."""
    import scipy.io

    from seqvpr.data.sources import load_traversal

    struct = scipy.io.loadmat(d / "db" / "route.db", squeeze_me=True)["dbStruct"]
    for role, count, npy in (("reference", "numImages", "route_database.npy"), ("query", "numQueries", "route_query.npy")):
        back = load_traversal(d / "db" / "route.toml", role)
        assert len(back) == int(struct[count])
        assert (d / "db" / npy).exists() == (back.descriptors is not None) == (npy in (d / "db" / "route.toml").read_text())


def _pair_check(folder: Path, stem: str) -> None:
    """The csv's figures are the ones the md shows."""
    with open(folder / f"{stem}.csv", newline="") as handle:
        figures = [float(row["R@1"]) for row in csv.DictReader(handle)]
    markdown = (folder / f"{stem}.md").read_text()
    assert figures and all(f"{f:.3f}" in markdown for f in figures)


def _route(d: Path, capsys) -> None:
    (d / "a").mkdir()
    write_route_files(d / "a", 60, 8, 1)


def _images(d: Path, capsys) -> None:
    """A route (descriptors and positions) and two small image folders (no descriptors, no positions)."""
    from PIL import Image

    _route(d, capsys)
    rng = np.random.default_rng(0)
    for side in ("ri", "qi"):
        (d / side).mkdir()
        for i in range(6):
            Image.fromarray(rng.integers(0, 255, (12, 16, 3), dtype=np.uint8)).save(d / side / f"{i:03d}.png")


def _map(d: Path, capsys) -> None:
    _route(d, capsys)
    assert run_cli(pytest.MonkeyPatch(), capsys, "map", "build", d / "a" / "ref.npz", "--out", d / "map")[0] == 0


def _map_check(d: Path, capsys) -> None:
    """The map opens whole, as built (one session) or grown (two), its files as map.json records them."""
    from seqvpr.maps.files import open_map

    saved = open_map(d / "map")
    assert saved.info.count in (60, 120) and len(saved.descriptors[:]) == saved.info.count
    assert run_cli(pytest.MonkeyPatch(), capsys, "map", "check", d / "map")[0] == 0


M = ("match", "-r", "{d}/a/ref.npz", "-q", "{d}/a/qry.npz", "--radius", "10m", "--out", "{d}/o")
L = ("localize", "--map", "{d}/map", "-q", "{d}/a/qry.npz", "--out", "{d}/lo")
C = ("convert", "--to", "dbstruct", "--out", "{d}/db/route.db")
#: writer: (inputs, old run, new run, the folder its output is in, the reader's check)
WRITERS = {
    "match": (_route, (*M, "-L", "3"), (*M, "-L", "5", "--velocities", "0.9,1.1"), "o", _match_check),
    "localize": (_map, (*L, "-L", "3", "--radius", "10m"), (*L, "-L", "5"), "lo", _localize_check),
    "map add": (_route, ("map", "build", "{d}/a/ref.npz", "--out", "{d}/map"),
                ("map", "add", "{d}/map", "{d}/a/qry.npz"), "map", _map_check),
    "convert": (_images, (*C, "-r", "{d}/a/ref.npz", "-q", "{d}/a/qry.npz", "--radius", "10m"),
                (*C, "-r", "{d}/ri", "-q", "{d}/qi", "--radius", "2f"), "db", _convert_check),
    "benchmark tables": (None, ("@tables", "{d}/b", "old"), ("@tables", "{d}/b", "new"), "b",
                         lambda d, capsys: _pair_check(d / "b", "results")),
    "benchmark tables over plain files": (None, ("@plain", "{d}/b"), ("@tables", "{d}/b", "new"), "b",
                                          lambda d, capsys: _pair_check(d / "b", "results")),
    "ablation tables": (None, ("@ablation", "{d}/b", "old"), ("@ablation", "{d}/b", "new"), "b",
                        lambda d, capsys: _pair_check(d / "b", "ablation")),
}


def _run(args: list[str], capsys) -> None:
    """Run a writer (a command, or a table writer); a command that fails raises what it said."""
    if args[0] in FUNCTIONS:
        FUNCTIONS[args[0]](*args[1:])
        return
    code, _, err = run_cli(pytest.MonkeyPatch(), capsys, *args)
    if code != 0:
        raise Failed(err)


class Failed(Exception):
    """A command that exited non-zero (an injected OSError the command line said in one line)."""


def _state(folder: Path) -> dict[str, object]:
    """What a reader sees in ``folder``: every visible file (links followed) by name, with its content; what differs
    from run to run (latencies) left out."""
    seen: dict[str, object] = {}
    for path in sorted(folder.rglob("*")):
        name = str(path.relative_to(folder))
        if any(part.startswith(".") for part in Path(name).parts) or not path.is_file():
            continue
        if path.suffix == ".csv":
            with open(path, newline="") as handle:
                seen[name] = [{k: v for k, v in row.items() if not k.endswith("_ms")} for row in csv.DictReader(handle)]
        elif path.name == "run.json":
            seen[name] = {k: v for k, v in json.loads(path.read_text()).items() if k != "latency_ms"}
        else:
            seen[name] = path.read_bytes() if "report" not in name else None
    return seen


def _temporaries(folder: Path) -> list[str]:
    return [p.name for p in folder.parent.rglob("*") if seqvpr.io.TEMP_TAG in p.name]


@pytest.fixture
def writer(request, tmp_path, capsys):
    """The writer's inputs made, its old output written; (its new run, its folder, its check, the old state)."""
    make, old, new, folder, check = WRITERS[request.param]
    if make:
        make(tmp_path, capsys)
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "variant").mkdir()  # another command's output beside the tables
    (tmp_path / "b" / "variant" / "model.json").write_text("{}")
    _run([a.format(d=tmp_path) for a in old], capsys)
    check(tmp_path, capsys)
    return [a.format(d=tmp_path) for a in new], tmp_path / folder, check, _state(tmp_path / folder)


@pytest.mark.parametrize("writer", list(WRITERS), indirect=True)
def test_a_failed_commit_leaves_the_old_output_or_the_new(writer, tmp_path, capsys, monkeypatch):
    """The k-th commit rename fails, k = 1, 2, ... until the run completes: after each failure the folder is the
    old output or the new, whole, as its reader sees it, and no temporary is left."""
    new, folder, check, old = writer
    states, k = [], 0
    while True:
        k += 1
        fail = FailOn(k)
        with monkeypatch.context() as patch:
            patch.setattr(seqvpr.io, "rename", fail.rename)
            patch.setattr(seqvpr.io, "exchange", fail.exchange)
            try:
                _run(new, capsys)
            except (Injected, Failed):
                assert fail.calls == k  # it failed where the failure was injected, not elsewhere
                states.append(_state(folder))
                check(tmp_path, capsys)
                assert not _temporaries(folder), k
                continue
        break
    assert fail.calls < k and k > 1  # the last run completed without reaching k; the ones before each failed
    assert _state(folder) != old
    assert all(state in (old, _state(folder)) for state in states)
    check(tmp_path, capsys)
    assert not _temporaries(folder)
    if (tmp_path / "b" / "variant").exists():
        assert (tmp_path / "b" / "variant" / "model.json").read_text() == "{}"


def child() -> None:
    """A writer run as a user would, whose first commit rename blocks (it is killed there): argv is the file to
    create once blocked, then the run."""
    ready, args = sys.argv[1], sys.argv[2:]

    def blocked(*_: object) -> None:
        Path(ready).write_text(str(os.getpid()))
        time.sleep(600)

    seqvpr.io.rename = seqvpr.io.exchange = blocked
    if args[0] in FUNCTIONS:
        FUNCTIONS[args[0]](*args[1:])
        return
    from seqvpr.cli import main

    sys.argv = ["seqvpr", *args]
    main()


@pytest.mark.slow
@pytest.mark.parametrize("writer", list(WRITERS), indirect=True)
def test_a_killed_writer_leaves_the_old_output_and_its_temporary_is_swept(writer, tmp_path, capsys):
    """SIGKILL while the new output is being written: the folder is the old output; the next run removes the dead
    process's temporary and commits the new output."""
    new, folder, check, old = writer
    ready = tmp_path / "ready"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(ROOT)])}
    process = subprocess.Popen([sys.executable, "-c", "from tests.test_commits import child; child()", str(ready), *new],
                               cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while not ready.exists() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert ready.exists(), process.communicate(timeout=5)[1].decode()
    process.send_signal(signal.SIGKILL)
    process.wait(timeout=30)
    assert _state(folder) == old
    check(tmp_path, capsys)
    assert any(f"{seqvpr.io.TEMP_TAG}{process.pid}-" in name for name in _temporaries(folder))
    _run(new, capsys)
    assert not _temporaries(folder)
    assert _state(folder) != old
    check(tmp_path, capsys)


def test_links_a_killed_first_set_left_are_no_fault(tmp_path, capsys):
    """A first dbstruct set killed before its commit leaves links to nothing under its names: the next convert to
    the same --out is not refused (the links name what the set lacks) and commits the set."""
    _route(tmp_path, capsys)
    (tmp_path / "db").mkdir()
    for name in ("route.db", "route_query.npy", "route.toml"):
        (tmp_path / "db" / name).symlink_to(f".route.toml.set/{name}")
    _run([a.format(d=tmp_path) for a in (*C, "-r", "{d}/a/ref.npz", "-q", "{d}/a/qry.npz", "--radius", "10m")], capsys)
    _convert_check(tmp_path, capsys)
    assert (tmp_path / "db" / "route_query.npy").is_file()

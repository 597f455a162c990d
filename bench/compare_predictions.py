"""Proof that a refactor changes no prediction: run every method in every mode with one checkout's ``src/``, keep
the outputs, and byte-compare two such runs case by case.

Run from the repository root (CPU, one case at a time, one thread; about 13 minutes a run, plus about a minute to
train the small models once; 150 MB in OUT; needs ../shared/data):

    .venv/bin/python bench/compare_predictions.py run --src /path/to/old/src --out runs/old --models runs/cmp-models
    .venv/bin/python bench/compare_predictions.py run --src src --out runs/new --models runs/cmp-models
    .venv/bin/python bench/compare_predictions.py compare runs/old runs/new
    .venv/bin/python bench/compare_predictions.py both --old COMMIT --new src --out runs/cmp --models runs/cmp-models

``run`` calls the ``seqvpr`` CLI (``python -m seqvpr.cli``) with ``PYTHONPATH=SRC`` (the same interpreter for every
checkout; it checks that ``seqvpr`` is imported from SRC) and ``SEQVPR_THREADS`` = ``--threads`` (default 1). Cases,
on Nordland 64x32 (summer reference, winter query, ``--frames 17:2000``, ``--radius 1f``) and Gardens Point
HDC-DELF descriptors (day_left reference, night_right query, ``--radius 2f``), all at ``-L 5`` (no ``-L`` for
single, hmm and graph, which use L = 1):

* offline: every method, ``seqvpr match -r REF -q QUERY``;
* map / sharded: every method, ``seqvpr match --map MAP`` on ``seqvpr map build`` of the reference, and on that map
  split by ``seqvpr map shard --shards 3`` (matched by one process);
* shortlisted / sharded-shortlisted: single, matching and seqmatchnet with ``--shortlist 10`` (and matching with
  ``--shortlist-history 2``) once both maps have a flat index (``seqvpr map index --index flat``);
* streaming / streaming-shortlisted: ``seqvpr localize --map MAP`` with matching, single, seqmatchnet and hmm,
  exact and with ``--shortlist 10``.

Methods with a model get small ones trained once into ``--models`` (fixed seeds, one epoch; about a minute in all)
and reused: SeqMatchNet (seqmatchnet, whose maps are built through it; hvpr, casevpr on the plain map), SeqNet
(seqnet, hvpr, casevpr) and, on Nordland only, JIST (it describes images, and its map is built through it; Gardens
Point has descriptors only, so there jist runs without a model and its cases record the CLI's refusal). Each case
keeps, under OUT/CASE/: predictions.csv and
correspondences.csv (match), estimates.csv (localize: stream.csv less its ``*_ms`` latency columns, the only part
that changes from run to run), or refused.txt (``refused: <the one error line>``, paths written as OUT, SRC, DATA,
MODELS) where the CLI refuses the mode; failed.txt marks a crash. ``compare OLD NEW`` prints one line per case
(same, ``DIFFERENT (n rows differ)``, missing) and a summary, exit status 1 unless every case is the same. ``both``
checks COMMIT out into a temporary ``git worktree add --detach``, runs it and NEW into OUT/old and OUT/new, compares
them and removes the worktree.
"""

from __future__ import annotations

import argparse
import csv
import itertools
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from _common import cpu_model

METHODS = ("single", "matching", "seqmatchnet", "adaptive", "seqslam", "seqslam-cone", "seqslam-hybrid", "smoothing",
           "delta", "concat", "seqgem", "seqgem-signed", "seqnet", "jist", "hvpr", "casevpr", "hmm", "graph")
SHORTLIST_METHODS = ("single", "matching", "seqmatchnet")
STREAM_METHODS = ("matching", "single", "seqmatchnet", "hmm")
MODELS_OF = {"seqmatchnet": ("seqmatchnet",), "seqnet": ("seqnet",), "jist": ("jist",),
             "hvpr": ("seqnet", "seqmatchnet"), "casevpr": ("seqnet", "seqmatchnet")}
MAP_MODELS = {"seqmatchnet": "seqmatchnet", "jist": "jist"}  # method -> the model its map is built through
QUICK_METHODS = ("single", "matching", "seqgem", "seqnet", "hmm")
SINGLE_FRAME = ("single", "hmm", "graph")  # methods that take no -L
SHORTLIST = ("--shortlist", "10")
KEPT = ("predictions.csv", "correspondences.csv")
JUDGED = ("predictions.csv", "estimates.csv", "refused.txt")  # a complete case holds one of these
GP_DESCRIPTORS = "gardenspoint_delf_hdc/descriptors/GardensPointWalking/{}/delf_hdc_4096_ortho_sigma_nx5ny7.mat"


@dataclass(frozen=True)
class Dataset:
    """One reference/query pair: the options every match and localize takes, and how its models are trained."""

    name: str
    reference: str
    query: str
    frames: tuple[str, ...]
    radius: str
    train: tuple[str, ...]
    images: bool

    def options(self, method: str) -> list[str]:
        """--frames, --radius and -L 5 (no -L for the methods that use L = 1 and refuse another)."""
        length = [] if method in SINGLE_FRAME else ["-L", "5"]
        return [*self.frames, "--radius", self.radius, *length]


def datasets(data: Path) -> list[Dataset]:
    """Nordland (images, frames 17-1999, +-1 frame) and Gardens Point (HDC-DELF descriptors, +-2 frames)."""
    nordland = data / "nordland_64x32"
    return [Dataset("nordland", str(nordland / "summer"), str(nordland / "winter"), ("--frames", "17:2000"), "1f",
                    ("--train-frames", "17:1200", "--val-frames", "1200:1600"), True),
            Dataset("gardenspoint", str(data / GP_DESCRIPTORS.format("day_left")),
                    str(data / GP_DESCRIPTORS.format("night_right")), (), "2f",
                    ("--train-frames", "0:120", "--val-frames", "120:200"), False)]


@dataclass
class Runner:
    """Runs the seqvpr CLI of one checkout's src/ and files each case's outputs under ``out``."""

    src: Path
    out: Path
    data: Path
    models: Path
    threads: int
    failures: list[str] = field(default_factory=list)

    @property
    def work(self) -> Path:
        return self.out / "_work"

    def env(self) -> dict[str, str]:
        return {**os.environ, "PYTHONPATH": str(self.src), "SEQVPR_THREADS": str(self.threads),
                "OMP_NUM_THREADS": str(self.threads), "PYTHONHASHSEED": "0"}

    def cli(self, *args: str | Path) -> subprocess.CompletedProcess:
        """One ``seqvpr`` command, in the work folder, output captured."""
        self.work.mkdir(parents=True, exist_ok=True)
        return subprocess.run([sys.executable, "-m", "seqvpr.cli", *map(str, args)], cwd=self.work, env=self.env(),
                              capture_output=True, text=True, check=False)

    def plain(self, text: str) -> str:
        """The text with this run's folders named OUT, SRC, DATA, MODELS, so two runs' refusals compare equal."""
        for folder, name in ((self.models, "MODELS"), (self.data, "DATA"), (self.out, "OUT"), (self.src, "SRC")):
            text = text.replace(str(folder.resolve()), name).replace(str(folder), name)
        return text

    def check_src(self) -> None:
        """Refuse to measure anything but SRC's seqvpr."""
        done = subprocess.run([sys.executable, "-c", "import seqvpr; print(seqvpr.__file__)"], env=self.env(),
                              capture_output=True, text=True, check=False)
        found = Path(done.stdout.strip() or "?").resolve()
        if not found.is_relative_to(self.src.resolve()):
            raise SystemExit(f"seqvpr is imported from {found}, not from {self.src}: {done.stderr.strip()}")
        print(f"{cpu_model()}, {self.threads} thread(s); seqvpr from {found}", flush=True)


def refusal(done: subprocess.CompletedProcess) -> str | None:
    """The CLI's one error line when it refused (exit 2), else None."""
    lines = done.stderr.strip().splitlines()
    if done.returncode == 2 and lines and lines[-1].startswith("seqvpr: error:"):
        return lines[-1]
    return None


def setup(runner: Runner, *args: str | Path) -> str | None:
    """A step cases rely on (train, map build, shard, index): None when it worked, its refusal line when refused;
    anything else stops the run."""
    started = time.perf_counter()
    done = runner.cli(*args)
    line = refusal(done)
    if done.returncode not in (0, 2) or (done.returncode == 2 and line is None):
        raise SystemExit(f"seqvpr {' '.join(map(str, args))} failed (exit {done.returncode}):\n{done.stderr[-2000:]}")
    print(f"  setup {runner.plain(' '.join(map(str, args[:2])))}: {time.perf_counter() - started:.1f} s"
          f"{'  ' + runner.plain(line) if line else ''}", flush=True)
    return line


def record(runner: Runner, case: str, text: str, name: str) -> None:
    """Write one line as the case's only output (refused.txt or failed.txt)."""
    folder = runner.out / case
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name).write_text(runner.plain(text) + "\n")


def drop_latency(source: Path, target: Path) -> None:
    """stream.csv less its ``*_ms`` columns (per-frame latencies, the only run-to-run differences)."""
    with source.open(newline="") as f:
        rows = list(csv.reader(f))
    keep = [i for i, name in enumerate(rows[0]) if not name.endswith("_ms")]
    with target.open("w", newline="") as f:
        csv.writer(f, lineterminator="\n").writerows([[row[i] for i in keep] for row in rows])


def keep_outputs(scratch: Path, folder: Path) -> None:
    """Copy the files a case is judged by from its --out folder into OUT/CASE/."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in KEPT:
        if (scratch / name).exists():
            shutil.copyfile(scratch / name, folder / name)
    if (scratch / "stream.csv").exists():
        drop_latency(scratch / "stream.csv", folder / "estimates.csv")


def run_case(runner: Runner, case: str, args: list[str | Path], blocked: str | None = None) -> None:
    """One case: its outputs, its refusal, or (when a setup step it needs was refused) that step's refusal."""
    folder = runner.out / case
    shutil.rmtree(folder, ignore_errors=True)
    if blocked:
        record(runner, case, f"refused: {blocked}", "refused.txt")
        print(f"{case}: refused (setup)", flush=True)
        return
    scratch = runner.work / "scratch"
    shutil.rmtree(scratch, ignore_errors=True)
    started = time.perf_counter()
    done = runner.cli(*args, "--out", scratch)
    line = refusal(done)
    if line:
        record(runner, case, f"refused: {line}", "refused.txt")
    elif done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
        record(runner, case, f"failed (exit {done.returncode}): {tail}", "failed.txt")
        runner.failures.append(f"{case}: {runner.plain(done.stderr[-2000:])}")
    else:
        keep_outputs(scratch, folder)
    status = "refused" if line else "FAILED" if done.returncode else "ok"
    print(f"{case}: {status} {time.perf_counter() - started:.1f} s", flush=True)


def train_models(runner: Runner, dataset: Dataset) -> dict[str, Path]:
    """The small models of this dataset (trained into MODELS/NAME/KIND once, then reused): kind -> folder."""
    common = ["-r", dataset.reference, "-q", dataset.query, *dataset.train, "--radius", dataset.radius, "-L", "5"]
    recipes = {"seqmatchnet": ["--epochs", "1", "--out-dim", "256", "--seed", "1"],
               "seqnet": ["--epochs", "1", "--out-dim", "256", "--seed", "1"]}
    if dataset.images:
        recipes["jist"] = ["--epochs", "1", "--refreshes", "1", "--max-iterations", "3", "--images-per-batch", "16",
                           "--out-dim", "64", "--image-size", "64x32", "--cell-size", "2", "--min-images", "2",
                           "--seed", "1"]
    models = {}
    for kind, options in recipes.items():
        folder = runner.models / dataset.name / kind
        if not (folder / "model.safetensors").exists() or not (folder / "config.json").exists():
            shutil.rmtree(folder, ignore_errors=True)
            if setup(runner, "train", kind, *common, *options, "--out", folder):
                raise SystemExit(f"training {kind} on {dataset.name} was refused")
        models[kind] = folder
    return models


def model_options(method: str, models: dict[str, Path]) -> list[str | Path]:
    """``--model`` options of a method (none for a model this dataset has not got)."""
    return [item for kind in MODELS_OF.get(method, ()) if kind in models for item in ("--model", models[kind])]


def map_kind(method: str, models: dict[str, Path]) -> str:
    """Which map a method matches: the one built through its SeqMatchNet or JIST model, else the plain one (hvpr
    and casevpr refuse a SeqMatchNet-transformed map: they apply the model themselves)."""
    kind = MAP_MODELS.get(method, "plain")
    return kind if kind in models else "plain"


@dataclass
class Maps:
    """A dataset's maps by kind (plain, seqmatchnet, jist), sharded or not, and the refusal of any that failed."""

    folders: dict[tuple[str, bool], Path] = field(default_factory=dict)
    refused: dict[tuple[str, bool], str | None] = field(default_factory=dict)


def build_maps(runner: Runner, dataset: Dataset, models: dict[str, Path], kinds: list[str]) -> Maps:
    """Build each kind of map of the reference, and split each into 3 shards."""
    maps = Maps()
    for kind in kinds:
        folder = runner.work / "maps" / dataset.name / kind
        shutil.rmtree(folder.parent / f"{kind}-3", ignore_errors=True)
        shutil.rmtree(folder, ignore_errors=True)
        through = ["--model", models[kind]] if kind in models else []
        line = setup(runner, "map", "build", dataset.reference, *dataset.frames, *through, "--out", folder)
        sharded = folder.parent / f"{kind}-3"
        maps.folders[kind, False], maps.folders[kind, True] = folder, sharded
        maps.refused[kind, False] = line
        maps.refused[kind, True] = line or setup(runner, "map", "shard", folder, "--shards", "3", "--out", sharded)
    return maps


def index_maps(runner: Runner, maps: Maps) -> None:
    """Give every built map a flat frame index, for --shortlist (a refusal blocks that map's shortlisted cases)."""
    for key, folder in maps.folders.items():
        if not maps.refused[key]:
            maps.refused[key] = setup(runner, "map", "index", folder, "--index", "flat")


def map_cases(runner: Runner, dataset: Dataset, models: dict, maps: Maps, methods: tuple[str, ...]) -> None:
    """Every method on the whole map and on the sharded one."""
    for sharded, mode in ((False, "map"), (True, "sharded")):
        for method in methods:
            key = (map_kind(method, models), sharded)
            run_case(runner, f"{dataset.name}.{mode}.{method}",
                     ["match", "--map", maps.folders[key], "-q", dataset.query, *dataset.options(method),
                      "--method", method, *model_options(method, models)], maps.refused[key])


def shortlist_cases(runner: Runner, dataset: Dataset, models: dict, maps: Maps, methods: tuple[str, ...]) -> None:
    """Frame-matching methods shortlisted by the map's index (whole and sharded), and one with history."""
    for sharded, mode in ((False, "shortlisted"), (True, "sharded-shortlisted")):
        variants = [(method, "", [*SHORTLIST]) for method in SHORTLIST_METHODS if method in methods]
        variants.append(("matching", "-h2", [*SHORTLIST, "--shortlist-history", "2"]))
        for method, suffix, options in variants:
            key = (map_kind(method, models), sharded)
            run_case(runner, f"{dataset.name}.{mode}{suffix}.{method}",
                     ["match", "--map", maps.folders[key], "-q", dataset.query, *dataset.options(method),
                      "--method", method, *options,
                      *model_options(method, models)], maps.refused[key])


def stream_cases(runner: Runner, dataset: Dataset, models: dict, maps: Maps, methods: tuple[str, ...]) -> None:
    """The online localiser, exact and shortlisted, for the methods it takes."""
    for method in (m for m in STREAM_METHODS if m in methods):
        key = (map_kind(method, models), False)
        for mode, options in (("streaming", []), ("streaming-shortlisted", [*SHORTLIST])):
            run_case(runner, f"{dataset.name}.{mode}.{method}",
                     ["localize", "--map", maps.folders[key], "-q", dataset.query, *dataset.options(method),
                      "--method", method, *options, *model_options(method, models)], maps.refused[key])


def run_dataset(runner: Runner, dataset: Dataset, methods: tuple[str, ...], train: bool) -> None:
    """Every case of one dataset, one at a time."""
    print(f"{dataset.name}:", flush=True)
    models = train_models(runner, dataset) if train else {}
    for method in methods:
        run_case(runner, f"{dataset.name}.offline.{method}",
                 ["match", "-r", dataset.reference, "-q", dataset.query, *dataset.options(method), "--method", method,
                  *model_options(method, models)])
    kinds = ["plain", *sorted({map_kind(m, models) for m in methods} - {"plain"})]
    maps = build_maps(runner, dataset, models, kinds)
    map_cases(runner, dataset, models, maps, methods)
    index_maps(runner, maps)
    shortlist_cases(runner, dataset, models, maps, methods)
    stream_cases(runner, dataset, models, maps, methods)


def clear_cases(out: Path, names: list[str]) -> None:
    """Remove an earlier run's case folders from OUT (only folders named DATASET.MODE.METHOD), so none is stale."""
    if out.is_dir():
        for folder in out.iterdir():
            if folder.is_dir() and folder.name.count(".") == 2 and folder.name.split(".")[0] in names:
                shutil.rmtree(folder)


def run(src: Path, out: Path, data: Path, models: Path, threads: int, quick: bool) -> int:
    """Run every case (``quick``: a handful on Gardens Point, no models) with SRC's seqvpr into OUT; 1 when a case
    crashed (its stderr is printed), else 0."""
    runner = Runner(src.resolve(), out.resolve(), data.resolve(), models.resolve(), threads)
    runner.check_src()
    started = time.perf_counter()
    chosen = datasets(runner.data)[1:] if quick else datasets(runner.data)
    clear_cases(runner.out, [d.name for d in datasets(runner.data)])
    for dataset in chosen:
        run_dataset(runner, dataset, QUICK_METHODS if quick else METHODS, train=not quick)
    shutil.rmtree(runner.work / "scratch", ignore_errors=True)
    cases = [p for p in runner.out.iterdir() if p.is_dir() and not p.name.startswith("_")]
    refused = sum((p / "refused.txt").exists() for p in cases)
    empty = [p.name for p in cases if not any((p / name).exists() for name in JUDGED)]
    print(f"{len(cases)} cases, {refused} refused, {len(runner.failures)} failed, {len(empty)} without an output "
          f"{' '.join(empty)}; {time.perf_counter() - started:.0f} s", flush=True)
    if runner.failures:
        print("failed cases:\n" + "\n".join(runner.failures), file=sys.stderr)
    return 1 if runner.failures else 0


def rows_differ(old: Path, new: Path) -> int:
    """Lines that differ between two files, position by position (a missing line counts)."""
    a, b = old.read_bytes().splitlines(), new.read_bytes().splitlines()
    return sum(x != y for x, y in itertools.zip_longest(a, b))


def compare_case(old: Path, new: Path) -> str:
    """``same``, ``DIFFERENT (n rows differ)`` or ``missing (...)`` for one case folder."""
    if not old.is_dir() or not new.is_dir():
        return f"missing (in {'old' if not old.is_dir() else 'new'})"
    names = sorted({p.name for p in old.iterdir()} | {p.name for p in new.iterdir()})
    differ = 0
    for name in names:
        if not (old / name).exists() or not (new / name).exists():
            return f"DIFFERENT ({name} only in {'old' if (old / name).exists() else 'new'})"
        if (old / name).read_bytes() != (new / name).read_bytes():
            differ += max(rows_differ(old / name, new / name), 1)
    return f"DIFFERENT ({differ} rows differ)" if differ else "same"


def compare(old: Path, new: Path) -> int:
    """Print one line per case and a summary; 1 unless every case is the same in both runs."""
    cases = sorted({p.name for root in (old, new) if root.is_dir() for p in root.iterdir()
                    if p.is_dir() and not p.name.startswith("_")})
    verdicts = [compare_case(old / case, new / case) for case in cases]
    for case, verdict in zip(cases, verdicts):
        print(f"{case}: {verdict}")
    same = verdicts.count("same")
    missing = sum(v.startswith("missing") for v in verdicts)
    print(f"{len(cases)} cases: {same} same, {len(cases) - same - missing} different, {missing} missing")
    return 0 if cases and same == len(cases) else 1


def both(commit: str, new: Path, out: Path, data: Path, models: Path, threads: int, quick: bool) -> int:
    """Check COMMIT out into a temporary worktree, run it and NEW into OUT/old and OUT/new, compare them (1 when a
    case differs or crashed)."""
    repo = Path(__file__).resolve().parents[1]
    tree = Path(tempfile.mkdtemp(prefix="seqvpr-old-")) / "tree"
    subprocess.run(["git", "-C", str(repo), "worktree", "add", "--detach", str(tree), commit], check=True)
    try:
        crashed = run(tree / "src", out / "old", data, models, threads, quick)
    finally:
        subprocess.run(["git", "-C", str(repo), "worktree", "remove", "--force", str(tree)], check=False)
        shutil.rmtree(tree.parent, ignore_errors=True)
    crashed |= run(new, out / "new", data, models, threads, quick)
    return compare(out / "old", out / "new") | crashed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    for name in ("run", "both"):
        sub = commands.add_parser(name)
        if name == "run":
            sub.add_argument("--src", type=Path, required=True, help="The checkout's src/ folder to measure.")
        else:
            sub.add_argument("--old", required=True, help="The commit before the change.")
            sub.add_argument("--new", type=Path, required=True, help="The src/ folder after it.")
        sub.add_argument("--out", type=Path, required=True)
        sub.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
        sub.add_argument("--models", type=Path, default=Path("runs/compare-models"),
                         help="Where the small models are trained once and reused.")
        sub.add_argument("--threads", type=int, default=1, help="SEQVPR_THREADS of every command.")
        sub.add_argument("--quick", action="store_true", help="A handful of cases, to try the script.")
    sub = commands.add_parser("compare")
    sub.add_argument("old", type=Path)
    sub.add_argument("new", type=Path)
    args = parser.parse_args()
    if args.command == "run":
        sys.exit(run(args.src, args.out, args.data, args.models, args.threads, args.quick))
    elif args.command == "compare":
        sys.exit(compare(args.old, args.new))
    else:
        sys.exit(both(args.old, args.new, args.out, args.data, args.models, args.threads, args.quick))


if __name__ == "__main__":
    main()

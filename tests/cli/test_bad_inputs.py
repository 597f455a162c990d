"""Every bad input a user can give: one line on stderr naming the file, field or option, exit status 2, and no
partial output under ``--out``. One row a case: the command, a fragment of the message (and the exit status when
not 2). The failures issue 16 listed are here by name."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from seqvpr.data.sources import save_traversal_npz
from seqvpr.data.traversal import Traversal
from tests.helpers import QuietCapsys, run_bad_case, run_cli, write_route_files


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """Files for every case: good traversals, broken ones, images, predictions, descriptions, a map."""
    w = tmp_path_factory.mktemp("bad")
    write_route_files(w, 80, 16, 2)
    rng = np.random.default_rng(0)
    save_traversal_npz(w / "ref32.npz", Traversal.from_descriptors(rng.random((80, 32), dtype=np.float32), "r32"))
    nan = rng.random((80, 16)).astype(np.float32)
    nan[5, 3] = np.nan
    np.save(w / "nan.npy", nan)
    np.save(w / "empty.npy", np.zeros((0, 16), np.float32))
    np.save(w / "flat.npy", np.zeros(16, np.float32))
    (w / "text.npy").write_text("not an array")
    (w / "afile").write_text("a file, not a folder")
    for name in ("imgs", "imgs_bad"):
        (w / name).mkdir()
        for i in range(6):
            Image.fromarray(rng.integers(0, 255, (32, 64, 3), dtype=np.uint8)).save(w / name / f"{i:03d}.png")
    (w / "imgs_bad" / "002.png").write_bytes((w / "imgs" / "002.png").read_bytes()[:80])  # truncated
    (w / "imgs_bad" / "004.png").write_text("text named .png")
    (w / "noimages").mkdir()
    (w / "preds_dup.csv").write_text("query,references,distances\n3,1 2,0.1 0.2\n3,5 6,0.1 0.2\n")
    (w / "preds_nan.csv").write_text("query,references,distances\n3,1 2,nan 0.2\n")
    (w / "preds_cols.csv").write_text("q,refs\n3,1\n")
    (w / "preds_ghost.csv").write_text("query,references,distances\n3,999,0.1\n")
    (w / "typo.toml").write_text('[reference]\ndescriptors = "ref.npz"\n[query]\ndescriptors = "qry.npz"\n'
                                 '[ground_truth]\nraduis = "10m"\n')
    (w / "table.toml").write_text('[refrence]\ndescriptors = "ref.npz"\n')
    (w / "bad.toml").write_text("[reference\n")
    np.save(w / "gt_wrong.npy", np.ones((3, 4), bool))
    (w / "seqb.txt").write_text("0 5\n")
    (w / "not_a_model").mkdir()
    (w / "junk.pth").write_bytes(b"junk")
    np.save(w / "complex.npy", rng.random((80, 16)) + 1j)
    (w / "mine").mkdir()
    (w / "mine" / "notes.txt").write_text("a user's own file")
    (w / "badshards").mkdir()
    (w / "badshards" / "shards.json").write_text('{"format": "seqvpr-sharded-map", "version": 1, "shards": "x"}')
    (w / "dangling").symlink_to(w / "nowhere")
    base = np.load(w / "ref.npz")
    np.savez(w / "ts_nan.npz", descriptors=base["descriptors"], timestamps=np.r_[np.nan, np.arange(79.0)])
    np.savez(w / "dup_index.npz", descriptors=base["descriptors"], frame_index=np.zeros(80, np.int64))
    import scipy.io

    scipy.io.savemat(w / "gt_nan.mat", {"GT": {"GThard": np.full((80, 80), np.nan)}})
    np.savez(w / "gt_multi.npz", aaa=np.zeros((80, 80), bool), zzz=np.eye(80, dtype=bool))
    (w / "onlydb" / "database").mkdir(parents=True)
    for i in range(3):
        Image.fromarray(rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)).save(
            w / "onlydb" / "database" / f"@{100 + i}@{200 + i}@.jpg")
    (w / "zero.npy").write_bytes(b"")
    (w / "zero.mat").write_bytes(b"")
    np.savez(w / "pos_text.npz", descriptors=rng.random((80, 16)).astype(np.float32), positions=np.array(["a"] * 80))
    (w / "self.toml").write_text('[reference]\ndescriptors = "self.toml"\n')
    (w / "int.toml").write_text('[reference]\ndescriptors = 5\n')
    (w / "preds_utf16.csv").write_text("query,references,distances\n3,1,0.1\n", encoding="utf-16")
    (w / "preds_huge.csv").write_text("query,references,distances\n3,99999999999999999999999,0.1\n")
    (w / "preds_neg.csv").write_text("query,references,distances\n3,-4,0.1\n")
    (w / "state.npz").write_bytes(b"PK\x03\x04 not really")
    (w / "bench.toml").write_text('[[dataset]]\nname = "a"\nreference = "ref.npz"\nquery = "qry.npz"\nradius = "10m"\n'
                                  'train = "0:40"\nselect = "40:60"\ntest = "60:80"\n[benchmark]\nks = ["one"]\n')
    np.savez(w / "far.npz", descriptors=base["descriptors"], positions=np.c_[np.full(80, 1e300), np.arange(80.0)])
    (w / "junk.bag").write_text("junk")
    (w / "badyaml").mkdir()
    (w / "badyaml" / "metadata.yaml").write_text("rosbag2_bagfile_information: [\n")
    (w / "junk.onnx").write_bytes(b"not an onnx model")
    (w / "inner").mkdir()
    (w / "bench_inner.toml").write_text((w / "bench.toml").read_text().replace('"ref.npz"', '"inner/ref.npz"')
                                        .replace('ks = ["one"]', "ks = [1]"))
    (w / "bench_typo.toml").write_text((w / "bench.toml").read_text().replace('ks = ["one"]', "kz = [1]"))
    (w / "escape.toml").write_text((w / "bench.toml").read_text().replace('name = "a"', 'name = "../../escape"')
                                   .replace('ks = ["one"]', "ks = [1]"))
    assert run_cli(pytest.MonkeyPatch(), QuietCapsys(), "map", "build", w / "ref.npz", "--out", w / "map")[0] == 0
    return w



M = ("match", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m")
CASES = {
    # --- match: files and shapes
    "match: missing reference": (("match", "-r", "{w}/nope.npz", "-q", "{w}/qry.npz", "--radius", "10m"), "nope.npz"),
    "match: empty .npy (was exit 130, 'aborted')": (("match", "-r", "{w}/empty.npy", "-q", "{w}/qry.npz", "--radius", "2f"), "empty.npy"),
    "match: text file named .npy": (("match", "-r", "{w}/text.npy", "-q", "{w}/qry.npz", "--radius", "2f"), "text.npy"),
    "match: 1-D descriptors": (("match", "-r", "{w}/flat.npy", "-q", "{w}/qry.npz", "--radius", "2f"), "flat.npy"),
    "match: NaN descriptors": (("match", "-r", "{w}/nan.npy", "-q", "{w}/qry.npz", "--radius", "2f"), "nan.npy"),
    "match: dimensions differ": (("match", "-r", "{w}/ref32.npz", "-q", "{w}/qry.npz", "--radius", "10m"), "32"),
    "match: L longer than every segment": ((*M, "-L", "500"), "longer than every segment"),
    "match: L zero": ((*M, "-L", "0"), "--seq-len"),
    "match: negative k": ((*M, "--k", "0"), "--k"),
    "match: bad radius": (("match", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "ten"), "radius"),
    "match: --radius with --ground-truth (was silently ignored)": ((*M, "--ground-truth", "{w}/gt_wrong.npy"), "not both"),
    "match: GT of the wrong size": (("match", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--ground-truth", "{w}/gt_wrong.npy"), "gt_wrong.npy"),
    "match: missing GT file": (("match", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--ground-truth", "{w}/gt.mat"), "gt.mat"),
    "match: unknown method (was a usage block)": ((*M, "--method", "nope"), "'--method'"),
    "match: unknown descriptor (was a usage block)": (("match", "-r", "{w}/imgs", "-q", "{w}/imgs", "--radius", "2f", "--descriptor", "vgg"), "vgg"),
    "match: unknown option": ((*M, "--bogus"), "--bogus"),
    "match: bad velocities": ((*M, "-L", "5", "--velocities", "0"), "velocit"),
    "match: bad memory budget": ((*M, "--memory-budget", "lots"), "lots"),
    "match: --out is a file (was a traceback, after the work)": ((*M, "--out", "{w}/afile"), "afile is not a folder"),
    "match: --out under a file": ((*M, "--out", "{w}/afile/sub"), "lies under"),
    "match: --out in /proc": ((*M, "--out", "/proc/seqvpr-out"), "nothing can be written"),
    "match: --out /dev/null": ((*M, "--out", "/dev/null"), "/dev/null is not a folder"),
    "match: --cache-dir is a file (was a traceback)": (("match", "-r", "{w}/imgs", "-q", "{w}/imgs", "--radius", "2f", "--descriptor", "efficientnet-lite0", "--cache-dir", "{w}/afile"), "--cache-dir"),
    "match: --cache-dir under a file": (("match", "-r", "{w}/imgs", "-q", "{w}/imgs", "--radius", "2f", "--cache-dir", "{w}/afile/c"), "lies under"),
    "match: --cache-dir with patchnorm (was silently ignored)": (("match", "-r", "{w}/imgs", "-q", "{w}/imgs", "--radius", "2f", "--cache-dir", "{w}/cache"), "not cached"),
    "match: --device cuda on a CPU torch": ((*M, "--device", "cuda"), "cuda"),
    "match: truncated image without --skip-bad": (("match", "-r", "{w}/imgs", "-q", "{w}/imgs_bad", "--radius", "2f"), "002.png"),
    "match: folder without images": (("match", "-r", "{w}/noimages", "-q", "{w}/imgs", "--radius", "2f"), "no images"),
    "match: reference and map both": (("match", "-r", "{w}/ref.npz", "--map", "{w}/map", "-q", "{w}/qry.npz", "--radius", "10m"), "one of them"),
    "match: misspelt dataset.toml key (was ignored)": (("match", "-r", "{w}/typo.toml", "-q", "{w}/typo.toml"), "'raduis'"),
    "match: unknown dataset.toml table": (("match", "-r", "{w}/table.toml", "-q", "{w}/qry.npz", "--radius", "2f"), "[refrence]"),
    "match: dataset.toml not TOML": (("match", "-r", "{w}/bad.toml", "-q", "{w}/qry.npz", "--radius", "2f"), "not valid TOML"),
    "match: bad --frames": ((*M, "--frames", "abc"), "frames"),
    "match: --frames beyond the traversal": ((*M, "--frames", "500:600"), "frames"),
    "match: missing model folder": ((*M, "--model", "{w}/nomodel"), "nomodel"),
    "match: a folder that is not a model": ((*M, "--model", "{w}/not_a_model"), "not_a_model"),
    "match: --shortlist without a map": ((*M, "--shortlist", "5"), "--shortlist"),
    "match: map without an index and --shortlist": (("match", "--map", "{w}/map", "-q", "{w}/qry.npz", "--radius", "10m", "--shortlist", "4"), "has no index"),
    "match: not a map": (("match", "--map", "{w}/noimages", "-q", "{w}/qry.npz", "--radius", "10m"), "not a seqvpr map"),
    "match: map of another dimension": (("match", "--map", "{w}/map", "-q", "{w}/ref32.npz", "--radius", "2f"), "32-D"),
    # --- eval
    "eval: duplicate query rows (the later silently won)": (("eval", "{w}/preds_dup.csv", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m"), "query 3 again"),
    "eval: NaN distances (were accepted)": (("eval", "{w}/preds_nan.csv", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m"), "NaN"),
    "eval: missing columns": (("eval", "{w}/preds_cols.csv", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m"), "missing column"),
    "eval: a reference frame that does not exist": (("eval", "{w}/preds_ghost.csv", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m"), "999"),
    "eval: missing predictions file": (("eval", "{w}/nope.csv", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m"), "nope.csv"),
    # --- extract
    "extract: truncated image without --skip-bad (--skip-bad did not skip)": (("extract", "{w}/imgs_bad", "--out", "{out}/d.npz"), "002.png"),
    "extract: --out is a folder": (("extract", "{w}/imgs", "--out", "{w}/imgs"), "is a folder"),
    "extract: --out under a file": (("extract", "{w}/imgs", "--out", "{w}/afile/d.npz"), "lies under"),
    "extract: descriptors, not images": (("extract", "{w}/ref.npz", "--out", "{out}/d.npz"), "ref.npz"),
    "extract: bad image size": (("extract", "{w}/imgs", "--descriptor", "efficientnet-lite0", "--image-size", "big", "--out", "{out}/d.npz"), "--image-size"),
    # --- train
    "train: unknown model kind": (("train", "nope"), "nope"),
    "train: --out is a file": (("train", "seqmatchnet", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m", "--out", "{w}/afile"), "afile is not a folder"),
    "train: overlapping splits": (("train", "seqmatchnet", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m", "--train-frames", "0:50", "--val-frames", "40:80", "--out", "{out}"), "overlap"),
    "train: negative epochs": (("train", "seqmatchnet", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m", "--train-frames", "0:50", "--val-frames", "50:80", "--epochs", "-1", "--out", "{out}"), "epochs"),
    # --- map
    "map build: missing source": (("map", "build", "{w}/nope.npz", "--out", "{out}"), "nope.npz"),
    "map build: unknown dtype": (("map", "build", "{w}/ref.npz", "--dtype", "int4", "--out", "{out}"), "int4"),
    "map build: bad index spec": (("map", "build", "{w}/ref.npz", "--index", "lsh", "--out", "{out}"), "lsh"),
    "map build: --out is a file": (("map", "build", "{w}/ref.npz", "--out", "{w}/afile"), "afile is not a folder"),
    "map info: not a map": (("map", "info", "{w}/noimages"), "not a seqvpr map"),
    # --- localize
    "localize: --calibrate without ground truth": (("localize", "--map", "{w}/map", "-q", "{w}/qry.npz", "--calibrate", "--out", "{out}"), "needs ground truth"),
    "localize: a query of another dimension": (("localize", "--map", "{w}/map", "-q", "{w}/ref32.npz", "--out", "{out}"), "16-D"),
    "localize: unknown method": (("localize", "--map", "{w}/map", "-q", "{w}/qry.npz", "--method", "delta", "--out", "{out}"), "'--method'"),
    "localize: --out is a file": (("localize", "--map", "{w}/map", "-q", "{w}/qry.npz", "--out", "{w}/afile"), "afile is not a folder"),
    # --- demo and import
    "demo: --out is a file": (("demo", "--out", "{w}/afile"), "afile is not a folder"),
    "demo: too few frames": (("demo", "--frames", "10", "--out", "{out}"), "--frames"),
    "import: not a checkpoint": (("import", "{w}/junk.pth", "--out", "{out}"), "junk.pth"),
    "import: missing checkpoint": (("import", "{w}/nope.pth", "--out", "{out}"), "nope.pth"),
    # --- found by probing: the general boundary (reading) and range-checked options, not case by case
    "match: complex descriptors (imaginary part was dropped)": (("match", "-r", "{w}/complex.npy", "-q", "{w}/qry.npz", "--radius", "2f"), "real numbers"),
    "match: zero-byte .npy (was exit 130)": (("match", "-r", "{w}/zero.npy", "-q", "{w}/qry.npz", "--radius", "2f"), "zero.npy"),
    "match: zero-byte .mat (was a traceback)": (("match", "-r", "{w}/zero.mat", "-q", "{w}/qry.npz", "--radius", "2f"), "zero.mat"),
    "match: positions that are text (was a traceback)": (("match", "-r", "{w}/pos_text.npz", "-q", "{w}/qry.npz", "--radius", "2f"), "pos_text.npz"),
    "match: a description naming itself (was a RecursionError)": (("match", "-r", "{w}/self.toml", "-q", "{w}/qry.npz", "--radius", "2f"), "names a description"),
    "match: a description value that is not text (was a traceback)": (("match", "-r", "{w}/int.toml", "-q", "{w}/qry.npz", "--radius", "2f"), "in quotes"),
    "match: --nprobe 0 (was a faiss traceback)": (("match", "--map", "{w}/map", "-q", "{w}/qry.npz", "--radius", "10m", "--nprobe", "0"), "'--nprobe'"),
    "match: --patch 0 (was a traceback)": (("match", "-r", "{w}/imgs", "-q", "{w}/imgs", "--radius", "2f", "--patch", "0"), "'--patch'"),
    "eval: UTF-16 predictions (was a traceback)": (("eval", "{w}/preds_utf16.csv", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m"), "preds_utf16.csv"),
    "eval: an index beyond int64 (was an OverflowError)": (("eval", "{w}/preds_huge.csv", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m"), "preds_huge.csv"),
    "eval: a negative reference row": (("eval", "{w}/preds_neg.csv", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m"), ">= 0"),
    "eval: a predictions path that is a folder (was a traceback)": (("eval", "{w}/imgs", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m"), "imgs"),
    "match: a zero-byte GT .mat (was a traceback)": (("match", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--ground-truth", "{w}/zero.mat"), "zero.mat"),
    "localize: a damaged state file (was a traceback)": (("localize", "--map", "{w}/map", "-q", "{w}/qry.npz", "--resume-state", "{w}/state.npz", "--out", "{out}"), "state.npz"),
    "localize: --floor nan": (("localize", "--map", "{w}/map", "-q", "{w}/qry.npz", "--method", "hmm", "--floor", "nan", "--out", "{out}"), "not a finite number"),
    "map build: negative --seed (was a traceback after the map was written)": (("map", "build", "{w}/ref.npz", "--index", "ivf:4", "--seed", "-1", "--out", "{out}"), "'--seed'"),
    "train: negative --momentum (was a traceback)": (("train", "seqmatchnet", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m", "--train-frames", "0:50", "--val-frames", "50:80", "--momentum", "-1", "--out", "{out}"), "'--momentum'"),
    "train: NaN --margin (was accepted)": (("train", "seqmatchnet", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m", "--train-frames", "0:50", "--val-frames", "50:80", "--margin", "nan", "--out", "{out}"), "'--margin'"),
    "benchmark: ks that are not numbers (was a traceback)": (("benchmark", "{w}/bench.toml", "--out", "{out}"), "ks must be"),
    "map build: onto a folder of the user's files (they were deleted)": (("map", "build", "{w}/ref.npz", "--out", "{w}/mine"), "holds other files"),
    "match: --out an empty text (wrote into the current folder)": ((*M, "--out", ""), "an empty path"),
    "match: --out a dangling symbolic link (a traceback after the work)": ((*M, "--out", "{w}/dangling"), "symbolic link to nothing"),
    "benchmark: a dataset name that climbs out of --out": (("benchmark", "{w}/escape.toml", "--out", "{out}"), "plain name"),
    "match: a GT .mat of NaN (every pair was a positive)": (("match", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--ground-truth", "{w}/gt_nan.mat"), "GT.GThard must hold 0/1"),
    "match: a dense GT .npz of several arrays (the first was taken)": (("match", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--ground-truth", "{w}/gt_multi.npz", "--gt-layout", "ref-query"), "name the ground-truth array 'gt'"),
    "match: an @UTM root without queries/ (read the database twice)": (("match", "-r", "{w}/onlydb", "-q", "{w}/onlydb", "--radius", "3m"), "no queries/"),
    "match: NaN timestamps (were accepted)": (("match", "-r", "{w}/ts_nan.npz", "-q", "{w}/qry.npz", "--radius", "2f"), "timestamps"),
    "match: a frame_index naming one frame 80 times (were accepted)": (("match", "-r", "{w}/dup_index.npz", "-q", "{w}/qry.npz", "--radius", "2f"), "frame_index"),
    "train: --device tpu (was a traceback)": (("train", "seqmatchnet", "-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "10m", "--train-frames", "0:50", "--val-frames", "50:80", "--device", "tpu", "--out", "{out}"), "'--device'"),
    "match: --device meta (was a traceback)": ((*M, "--device", "meta"), "'--device'"),
    "match: a huge --thumbnail (was a MemoryError)": (("match", "-r", "{w}/imgs", "-q", "{w}/imgs", "--radius", "2f", "--thumbnail", "100000x100000"), "--thumbnail"),
    "localize: -L longer than every map segment (warmed up forever)": (("localize", "--map", "{w}/map", "-q", "{w}/qry.npz", "-L", "100000", "--out", "{out}"), "longer than every segment"),
    "benchmark: an unknown [benchmark] key (was ignored)": (("benchmark", "{w}/bench_typo.toml", "--out", "{out}"), "unknown keys"),
    "match: --steps MIN above MAX": ((*M, "--method", "adaptive", "-L", "3", "--steps", "3:1"), "--steps"),
    "match: --contrast-window 1": ((*M, "--method", "seqslam", "-L", "3", "--contrast-window", "1"), "--contrast-window"),
    "map shard: more shards than frames": (("map", "shard", "{w}/map", "--shards", "100000", "--out", "{out}"), "--shards must be between 1"),
    "map shard: onto a folder of the user's files": (("map", "shard", "{w}/map", "--shards", "2", "--out", "{w}/mine"), "holds other files"),
    "map shard: not a map": (("map", "shard", "{w}/noimages", "--shards", "2", "--out", "{out}"), "not a seqvpr map"),
    "match: a malformed shards.json": (("match", "--map", "{w}/badshards", "-q", "{w}/qry.npz", "--radius", "10m"), "malformed sharded map"),
    # --- outputs that would land on inputs (issue 44: one rule at every writer)
    "match: --out inside the reference's image folder": (("match", "-r", "{w}/imgs", "-q", "{w}/imgs", "--radius", "2f",
                                                          "--out", "{w}/imgs/run"), "lies inside the input"),
    "match: --out holding the map": (("match", "--map", "{w}/map", "-q", "{w}/qry.npz", "--radius", "10m", "--out", "{w}"),
                                     "holds the input"),
    "localize: --out inside the map folder": (("localize", "--map", "{w}/map", "-q", "{w}/qry.npz", "--out", "{w}/map/run"),
                                              "lies inside the input"),
    "match: --cache-dir an image folder": (("match", "-r", "{w}/imgs", "-q", "{w}/imgs", "--radius", "2f", "--descriptor",
                                            "efficientnet-lite0", "--cache-dir", "{w}/imgs"), "the descriptor cache"),
    "extract: --cache-dir inside the image folder": (("extract", "{w}/imgs", "--descriptor", "efficientnet-lite0",
                                                      "--cache-dir", "{w}/imgs/c", "--out", "{out}/d.npz"), "lies inside"),
    "benchmark: --out holding its config": (("benchmark", "{w}/bench.toml", "--out", "{w}"), "holds the input"),
    "benchmark: --out holding a dataset": (("benchmark", "{w}/bench_inner.toml", "--out", "{w}/inner"), "holds the input"),
    # --- positions that are wrong, and readers' errors (issue 44)
    "match: an easting of 1e300 (reached scipy and overflowed)": (("match", "-r", "{w}/far.npz", "-q", "{w}/qry.npz",
                                                                   "--radius", "5m"), "not a place"),
    "play: a file that is no bag (a rosbags traceback)": (("play", "{w}/junk.bag"), "junk.bag: not a readable bag"),
    "play: --rate 1e-300 (overflowed)": (("play", "{w}/junk.bag", "--rate", "1e-300"), "--rate must be from 0.001"),
    "match: a bag whose metadata.yaml does not parse (5-7 lines)": (("match", "-r", "{w}/badyaml", "-q", "{w}/qry.npz",
                                                                      "--radius", "5m"), "badyaml: not a readable bag"),
    "map build: a descriptor file whose positions are not numbers": (("map", "build", "{w}/pos_text.npz", "--out", "{out}"),
                                                                     "pos_text.npz"),
    # --- encoders and engines (issue 45)
    "extract: a damaged ONNX file": (("extract", "{w}/imgs", "--descriptor", "onnx:{w}/junk.onnx", "--image-size",
                                      "32x32", "--out", "{out}/d.npz"), "junk.onnx: not an ONNX model"),
    "extract: an ONNX file that is not there": (("extract", "{w}/imgs", "--descriptor", "onnx:{w}/nope.onnx", "--out",
                                                 "{out}/d.npz"), "nope.onnx"),
    "match: an engine seqvpr does not have": ((*M, "--engine", "tensorrt"), "'--engine'"),
    "export: a model folder that describes no images": (("export", "{w}/not_a_model", "--out", "{out}.onnx"),
                                                        "not_a_model"),
    # --- loop closures (issue 46)
    "loops: an exclusion without a unit": (("loops", "{w}/qry.npz", "--exclude", "30", "--out", "{out}"), "--exclude"),
    "loops: a negative exclusion": (("loops", "{w}/qry.npz", "--exclude=-5f", "--out", "{out}"), "must not be negative"),
    "loops: seconds for a drive without timestamps": (("loops", "{w}/ref32.npz", "--exclude", "10s", "--out", "{out}"),
                                                      "needs timestamps"),
    "loops: a radius in metres for a drive without positions": (("loops", "{w}/ref32.npz", "--radius", "5m", "--out",
                                                                 "{out}"), "no positions"),
    "loops: a method that does not step": (("loops", "{w}/qry.npz", "--method", "hmm", "--out", "{out}"), "'--method'"),
    "loops: a shortlist index that must be trained": (("loops", "{w}/qry.npz", "--shortlist", "5", "--shortlist-index",
                                                       "ivf:16", "--out", "{out}"), "--shortlist-index"),
    "view: a folder seqvpr did not write": (("view", "{w}/imgs", "--out", "{out}"), "not a folder seqvpr wrote"),
    "view: no such folder": (("view", "{w}/nowhere", "--out", "{out}"), "no such folder"),
    "view: a localisation beside a match": (("view", "{w}/imgs", "{w}/imgs", "--out", "{out}"), "not a folder"),
    "loops: a window longer than the drive": (("loops", "{w}/qry.npz", "-L", "500", "--out", "{out}"), "500"),
    # --- maps that grow (issue 46)
    "map add: frames of another dimension": (("map", "add", "{w}/map", "{w}/ref32.npz"), "32-D"),
    "map add: a source the map holds": (("map", "add", "{w}/map", "{w}/ref.npz"), "already in the map"),
    "map add: images to a map of descriptor files": (("map", "add", "{w}/map", "{w}/imgs"), "holds descriptor files"),
    "map add: a model the map was not built through": (("map", "add", "{w}/map", "{w}/qry.npz", "--model",
                                                        "{w}/not_a_model"), "not_a_model"),
    "map add: no such map": (("map", "add", "{w}/nomap", "{w}/qry.npz"), "nomap"),
    # --- the command itself
    "unknown command": (("nope",), "No such command"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_is_one_line_exit_2_and_no_partial_output(world, tmp_path, monkeypatch, capsys, case):
    args, fragment = CASES[case]
    out = tmp_path / "out"
    before = (world / "afile").read_text()
    run_bad_case(monkeypatch, capsys, args, fragment, world, out)
    assert (world / "afile").read_text() == before


def test_the_table_covers_at_least_fifty_cases():
    assert len(CASES) >= 50
    assert {args[0] for args, _ in CASES.values()} >= {"match", "eval", "extract", "train", "map", "demo", "import",
                                                        "localize"}


def test_skip_bad_skips_in_match_and_extract(world, tmp_path, monkeypatch, capsys):
    code, out, err = run_cli(monkeypatch, capsys, "extract", world / "imgs_bad", "--skip-bad", "--out", tmp_path / "d.npz")
    assert code == 0 and "skipped 2 unreadable images" in err, err
    code, out, err = run_cli(monkeypatch, capsys, "match", "-r", world / "imgs", "-q", world / "imgs_bad", "--skip-bad",
                             "--radius", "2f", "--json", "--out", tmp_path / "m")
    assert code == 0 and json.loads(out)["queries_evaluated"] == 4, err


def test_a_16_bit_png_is_described_not_zeroed(tmp_path, monkeypatch, capsys):
    """Was: an ``I;16`` PNG became an all-zero descriptor, exit 0, no warning."""
    rng = np.random.default_rng(1)
    folder = tmp_path / "wide"
    folder.mkdir()
    pixels = rng.integers(0, 65535, (32, 64)).astype(np.uint16)
    Image.fromarray(pixels).save(folder / "0.png")
    Image.fromarray((pixels >> 8).astype(np.uint8)).save(tmp_path / "narrow.png")
    assert Image.open(folder / "0.png").mode.startswith("I;16")
    for descriptor in ("patchnorm", "efficientnet-lite0"):
        code, _, err = run_cli(monkeypatch, capsys, "extract", folder, "--descriptor", descriptor, "--out",
                               tmp_path / f"{descriptor}.npz")
        assert code == 0, err
        rows = np.load(tmp_path / f"{descriptor}.npz")["descriptors"]
        assert np.isfinite(rows).all() and (np.abs(rows) > 0).mean() > 0.5
    from seqvpr.data.images import read_image

    np.testing.assert_allclose(np.asarray(read_image(folder / "0.png", "L"), float),
                               np.asarray(read_image(tmp_path / "narrow.png", "L"), float), atol=1)


def test_a_ground_truth_file_naming_missing_frames_is_flagged(world, tmp_path, monkeypatch, capsys):
    """Was: a GT file naming frames that do not exist was used silently."""
    positives = np.zeros((82, 80), bool)  # [n_reference + 2, n_query]: two reference frames the traversal lacks
    positives[np.arange(80), np.arange(80)] = True
    positives[81, 3] = True
    np.save(tmp_path / "gt.npy", positives)
    code, _, err = run_cli(monkeypatch, capsys, "match", "-r", world / "ref.npz", "-q", world / "qry.npz",
                           "--ground-truth", tmp_path / "gt.npy", "--gt-layout", "ref-query", "--out", tmp_path / "o")
    assert code == 0, err
    assert "seqvpr: warning:" in err and "names 1 reference frames the reference traversal lacks (81" in err


def test_a_map_build_onto_the_users_folder_keeps_their_files(world, tmp_path, monkeypatch, capsys):
    code, _, err = run_cli(monkeypatch, capsys, "map", "build", world / "ref.npz", "--out", world / "mine")
    assert code == 2 and (world / "mine" / "notes.txt").read_text() == "a user's own file", err


def test_descriptors_at_any_scale_match_alike(world, tmp_path, monkeypatch, capsys):
    """Float32 squares of 1e19 overflow and of 1e-25 underflow: normalisation must not care (R@1 was 0.013)."""
    descriptors = np.load(world / "ref.npz")["descriptors"].astype(np.float32)
    recalls = []
    for scale in (1.0, 1e19, 1e-25):
        np.save(tmp_path / "d.npy", descriptors * np.float32(scale))
        code, out, err = run_cli(monkeypatch, capsys, "match", "-r", tmp_path / "d.npy", "-q", tmp_path / "d.npy",
                                 "--radius", "0f", "--json", "--out", tmp_path / "o")
        assert code == 0, err
        recalls.append(json.loads(out)["recall"])
    assert recalls[0] == recalls[1] == recalls[2] and recalls[0]["1"] == 1.0, recalls


def test_json_with_no_scored_query_is_strict_json(world, tmp_path, monkeypatch, capsys):
    code, out, err = run_cli(monkeypatch, capsys, *[a.format(w=world) for a in M[:-1]], "0m", "--json",
                             "--out", tmp_path / "o")
    assert code == 0, err
    parsed = json.loads(out, parse_constant=lambda c: pytest.fail(f"{c} is not JSON"))
    assert parsed["recall"]["1"] is None


def test_no_output_lands_on_an_input(tmp_path, monkeypatch, capsys):
    """Every output a command writes, through a symbolic or hard link too, is refused where it is, lies inside or
    holds an input of the run (a map folder's files among them): one line, exit 2, the input as it was."""
    import os

    from seqvpr.localization import Localizer
    from seqvpr.maps import build_map, open_map
    from seqvpr.maps.sharding import shard_map
    from tests.helpers import raises_one_line, write_route_files

    route = write_route_files(tmp_path, n_frames=60, dim=8, seed=2)
    build_map([str(route / "ref.npz")], tmp_path / "map")
    os.link(tmp_path / "map" / "descriptors.npy", tmp_path / "rows-link.npy")
    (tmp_path / "qry-link.npz").symlink_to(route / "qry.npz")
    before = {p: p.read_bytes() for p in (tmp_path / "map").iterdir() if p.is_file()}
    query_bytes = (route / "qry.npz").read_bytes()
    common = ("localize", "--map", tmp_path / "map", "-q", route / "qry.npz", "--out", tmp_path / "run")
    for arguments, fragment in [
        ((*common, "--save-state", tmp_path / "map" / "map.json"), "lies inside the input"),
        ((*common, "--save-state", tmp_path / "rows-link.npy"), "is a file (a hard link) of the input"),
        ((*common, "--save-state", tmp_path / "qry-link.npz"), "--save-state"),
        (("convert", "-r", tmp_path / "qry-link.npz", "--to", "npz", "--out", route / "qry.npz"), "is the input"),
        (("convert", "-r", route / "qry.npz", "--to", "npz", "--out", route / "qry.npz"), "is the input"),
        (("map", "build", route / "ref.npz", "--out", route), "holds"),
        (("map", "shard", tmp_path / "map", "--shards", "2", "--out", tmp_path / "map" / "s"), "lies inside"),
    ]:
        code, _, err = run_cli(monkeypatch, capsys, *map(str, arguments))
        assert code == 2 and fragment in err and err.count("\n") == 1, (arguments, err)
    assert {p: p.read_bytes() for p in (tmp_path / "map").iterdir() if p.is_file()} == before
    assert (route / "qry.npz").read_bytes() == query_bytes and not (tmp_path / "run").exists()
    localizer = Localizer.open(open_map(tmp_path / "map"))
    raises_one_line("the state file", localizer.save_state, tmp_path / "map" / "descriptors.npy")
    raises_one_line("the map", build_map, str(route / "ref.npz"), route / "ref.npz")
    raises_one_line("the sharded map", shard_map, tmp_path / "map", tmp_path / "map" / "s", 2)
    assert build_map(str(route / "ref.npz"), tmp_path / "one").info.count == 60  # one path alone is one source
    from seqvpr.models.published import import_checkpoint

    (tmp_path / "ckpt").mkdir()
    (tmp_path / "ckpt" / "model.pth").write_bytes(b"not read: the output is checked first")
    raises_one_line("the model folder", import_checkpoint, tmp_path / "ckpt" / "model.pth", tmp_path / "ckpt")

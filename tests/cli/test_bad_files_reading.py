"""The operating system's oddities as inputs: a FIFO, a device or a folder named where a file belongs, and a zip bomb,
are one ``seqvpr: error`` line naming the file, exit 2, no partial output, and never a hang."""

from __future__ import annotations

import os
import signal
import zipfile

import numpy as np
import pytest
import torch
from PIL import Image

from tests.helpers import QuietCapsys, run_cli, write_route_files



@pytest.fixture(scope="module")
def world(tmp_path_factory):
    w = tmp_path_factory.mktemp("reading")
    write_route_files(w, 80, 16, 2)
    for name in ("fifo.npy", "fifo.npz", "fifo.toml", "fifo.pth", "fifo.csv", "fifo.txt", "fifo.mat", "fifo.json"):
        os.mkfifo(w / name)
    for folder in ("imgs", "imgs_fifo"):
        (w / folder).mkdir()
        for i in range(4):
            Image.fromarray(np.zeros((24, 32, 3), np.uint8)).save(w / folder / f"{i}.png")
    os.mkfifo(w / "imgs_fifo" / "positions.csv")
    (w / "fifo_side.toml").write_text('[reference]\ndescriptors = "fifo.npy"\n[query]\ndescriptors = "fifo.npy"\n'
                                      '[ground_truth]\nradius = "2f"\n')
    (w / "fifo_gt.toml").write_text('[reference]\ndescriptors = "ref.npz"\n[query]\ndescriptors = "qry.npz"\n'
                                    '[ground_truth]\nfile = "fifo.npy"\n')
    (w / "fifo_bounds.toml").write_text('[reference]\ndescriptors = "ref.npz"\nseq_bounds = "fifo.txt"\n'
                                        '[query]\ndescriptors = "qry.npz"\n[ground_truth]\nradius = "2f"\n')
    torch.save({"pool.0.conv.weight": torch.zeros(4, 16, 3), "pool.0.conv.bias": torch.zeros(4)}, w / "seqnet.pth")
    info = zipfile.ZipInfo("descriptors.npy")
    info.compress_type = zipfile.ZIP_DEFLATED
    with zipfile.ZipFile(w / "bomb.npz", "w") as archive:
        with archive.open(info, "w", force_zip64=True) as member:
            member.write(b"\0" * (1 << 16))
        archive.filelist[0].file_size = 1 << 40  # claims a TiB
    assert run_cli(pytest.MonkeyPatch(), QuietCapsys(), "map", "build", w / "ref.npz", "--out", w / "map")[0] == 0
    return w


R = ("-r", "{w}/ref.npz", "-q", "{w}/qry.npz", "--radius", "2f")
CASES = {
    "match: a FIFO as descriptors": (("match", "-r", "{w}/fifo.npy", "-q", "{w}/qry.npz", "--radius", "2f"), "fifo.npy: is a named pipe"),
    "match: a FIFO as a traversal .npz": (("match", "-r", "{w}/ref.npz", "-q", "{w}/fifo.npz", "--radius", "2f"), "fifo.npz: is a named pipe"),
    "match: a FIFO as descriptors .mat": (("match", "-r", "{w}/fifo.mat", "-q", "{w}/qry.npz", "--radius", "2f"), "fifo.mat: is a named pipe"),
    "match: a FIFO as a description": (("match", "-r", "{w}/fifo.toml", "-q", "{w}/qry.npz", "--radius", "2f"), "fifo.toml: is a named pipe"),
    "match: a description naming a FIFO": (("match", "-r", "{w}/fifo_side.toml", "-q", "{w}/fifo_side.toml"), "fifo.npy: is a named pipe"),
    "match: a FIFO as ground truth": (("match", *R[:4], "--ground-truth", "{w}/fifo.npy"), "fifo.npy: is a named pipe"),
    "match: a description naming a FIFO as ground truth": (("match", "-r", "{w}/fifo_gt.toml", "-q", "{w}/fifo_gt.toml"), "fifo.npy: is a named pipe"),
    "match: a description naming a FIFO as seq_bounds": (("match", "-r", "{w}/fifo_bounds.toml", "-q", "{w}/fifo_bounds.toml"), "fifo.txt: is a named pipe"),
    "match: a FIFO as positions.csv": (("match", "-r", "{w}/imgs_fifo", "-q", "{w}/imgs_fifo", "--radius", "2f"), "positions.csv: is a named pipe"),
    "match: a character device as descriptors": (("match", "-r", "/dev/zero", "-q", "{w}/qry.npz", "--radius", "2f"), "/dev/zero: is a character device"),
    "match: a zip bomb as a traversal": (("match", "-r", "{w}/bomb.npz", "-q", "{w}/qry.npz", "--radius", "2f"), "would decompress to 1024.0 GiB"),
    "eval: a FIFO as predictions": (("eval", "{w}/fifo.csv", *R), "fifo.csv: is a named pipe"),
    "import: a FIFO as a checkpoint": (("import", "{w}/fifo.pth", "--out", "{out}"), "fifo.pth: is a named pipe"),
    "import: a FIFO as flags.json": (("import", "{w}/seqnet.pth", "--flags", "{w}/fifo.json", "--out", "{out}"), "fifo.json: is a named pipe"),
    "extract: a FIFO as backbone weights": (("extract", "{w}/imgs", "--descriptor", "resnet18", "--weights", "{w}/fifo.pth", "--out", "{out}/d.npz"), "fifo.pth: is a named pipe"),
    "localize: a FIFO as a state": (("localize", "--map", "{w}/map", "-q", "{w}/qry.npz", "--resume-state", "{w}/fifo.npz", "--out", "{out}"), "fifo.npz: is a named pipe"),
    "map build: a FIFO as descriptors": (("map", "build", "{w}/fifo.npy", "--out", "{out}"), "fifo.npy: is a named pipe"),
}


def _hung(signum, frame):
    raise TimeoutError("seqvpr hung on an input")


@pytest.mark.parametrize("case", list(CASES))
def test_an_odd_file_is_one_line_and_never_hangs(world, tmp_path, monkeypatch, capsys, case):
    args, fragment = CASES[case]
    out = tmp_path / "out"
    previous = signal.signal(signal.SIGALRM, _hung)
    signal.alarm(30)  # a FIFO opened for reading would wait for a writer forever
    try:
        code, _, err = run_cli(monkeypatch, capsys, *(a.format(w=world, out=out) for a in args))
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    lines = [line for line in err.strip().splitlines() if line.startswith("seqvpr: error")]
    assert code == 2, f"exit {code}: {err}"
    assert len(lines) == 1 and "Traceback" not in err, err
    assert fragment in lines[0], lines[0]
    assert not out.exists() or not any(out.rglob("*")), f"partial output: {list(out.rglob('*'))}"

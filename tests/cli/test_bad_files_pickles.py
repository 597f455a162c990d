"""A pickle payload saved as every kind of file seqvpr reads (descriptors, traversals, ground truth, checkpoints,
backbone weights, a localiser state, a map's files), named on the command line and through a dataset description:
one ``seqvpr: error`` line naming the file, exit 2, no partial output, and the payload never runs. Big-endian
descriptors match exactly as native ones."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from PIL import Image

from tests.helpers import QuietCapsys, run_bad_case, run_cli, write_route_files
from tests.test_arrays import write_function_handle_mat


class Payload:
    """Unpickling this creates ``path``: the proof a reader ran code."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))



def objects(marker, shape) -> np.ndarray:
    """An object array whose every item is the payload."""
    values = np.empty(shape, dtype=object)
    values[...] = Payload(marker)
    return values


def evil_map(w, name: str, file: str) -> None:
    """A copy of the built map with ``file`` replaced by a pickle of its shape."""
    shutil.copytree(w / "map", w / name)
    np.save(w / name / file, objects(w / "PWNED", np.load(w / "map" / file, mmap_mode="r").shape[:1]))


def describe(w, name: str, descriptors: str, gt: str | None = None) -> None:
    """A dataset description whose sides are ``descriptors`` (and whose ground truth is ``gt``)."""
    text = f'[reference]\ndescriptors = "{descriptors}"\n[query]\ndescriptors = "{descriptors}"\n'
    text += f'[ground_truth]\nfile = "{gt}"\n' if gt else '[ground_truth]\nradius = "2f"\n'
    (w / name).write_text(text)


def exported_with_payload(path, marker) -> None:
    """A torch.export file whose sample inputs (a pickle inside the archive) carry the payload."""
    import io
    import zipfile

    program = torch.export.export(torch.nn.Linear(3, 4), (torch.zeros(2, 3),))
    torch.export.save(program, path.with_suffix(".good.pt2"))
    payload = io.BytesIO()
    torch.save(((Payload(marker),), {}), payload)
    with zipfile.ZipFile(path.with_suffix(".good.pt2")) as good, zipfile.ZipFile(path, "w") as evil:
        for info in good.infolist():
            evil.writestr(info, payload.getvalue() if info.filename.endswith("sample_inputs/model.pt")
                          else good.read(info.filename))


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    w = tmp_path_factory.mktemp("pickles")
    marker = w / "PWNED"
    write_route_files(w, 80, 16, 2)
    good = np.load(w / "ref.npz")["descriptors"]
    np.save(w / "good.npy", good)
    np.save(w / "evil.npy", objects(marker, (80, 16)))
    np.savez(w / "evil_trav.npz", descriptors=objects(marker, (80, 16)))
    np.savez(w / "evil_member.npz", descriptors=good, positions=objects(marker, (80, 2)))
    rows = np.empty((80, 2), dtype=object)
    rows[:, 0] = np.arange(80)
    rows[:, 1] = [[i] for i in range(80)]
    rows[3, 1] = [Payload(marker)]
    np.save(w / "evil_gt.npy", rows)  # VPR-Bench's layout, one row carrying the payload
    np.savez(w / "evil_gt.npz", gt=objects(marker, (80, 80)))
    write_function_handle_mat(w / "handle.mat", "Y")
    write_function_handle_mat(w / "handle_gt.mat", "GT")
    torch.save({"state_dict": {"pool.0.conv.weight": torch.zeros(4, 16, 3)}, "epoch": Payload(marker)}, w / "evil.pth")
    (w / "imgs").mkdir()
    for i in range(4):
        Image.fromarray(np.zeros((24, 32, 3), np.uint8)).save(w / "imgs" / f"{i}.png")
    exported_with_payload(w / "evil.pt2", marker)
    np.savez(w / "evil_state.npz", header=np.array("{}"), matcher_x=objects(marker, (3,)))
    assert run_cli(pytest.MonkeyPatch(), QuietCapsys(), "map", "build", w / "ref.npz", "--out", w / "map")[0] == 0
    evil_map(w, "map_desc", "descriptors.npy")
    evil_map(w, "map_seg", "segments.npy")
    describe(w, "desc.toml", "evil.npy")
    describe(w, "trav.toml", "evil_trav.npz")
    describe(w, "member.toml", "evil_member.npz")
    describe(w, "gt_npy.toml", "good.npy", "evil_gt.npy")
    describe(w, "gt_npz.toml", "good.npy", "evil_gt.npz")
    describe(w, "mat.toml", "handle.mat")
    describe(w, "gt_mat.toml", "good.npy", "handle_gt.mat")
    assert not marker.exists()
    return w


Q = ("-q", "{w}/qry.npz")
CASES = {
    # --- named on the command line
    "match: descriptors .npy": (("match", "-r", "{w}/evil.npy", *Q, "--radius", "2f"), "evil.npy"),
    "match: traversal .npz": (("match", "-r", "{w}/evil_trav.npz", *Q, "--radius", "2f"), "evil_trav.npz"),
    "match: a traversal .npz member": (("match", "-r", "{w}/ref.npz", "-q", "{w}/evil_member.npz", "--radius", "2f"), "evil_member.npz"),
    "match: ground truth .npy (VPR-Bench rows)": (("match", "-r", "{w}/good.npy", "-q", "{w}/good.npy", "--ground-truth", "{w}/evil_gt.npy"), "evil_gt.npy"),
    "match: ground truth .npz": (("match", "-r", "{w}/good.npy", "-q", "{w}/good.npy", "--ground-truth", "{w}/evil_gt.npz", "--gt-layout", "ref-query"), "evil_gt.npz"),
    "match: descriptors .mat holding a function handle": (("match", "-r", "{w}/handle.mat", *Q, "--radius", "2f"), "handle.mat: variable 'Y' is a function handle"),
    "match: ground truth .mat holding a function handle": (("match", "-r", "{w}/good.npy", "-q", "{w}/good.npy", "--ground-truth", "{w}/handle_gt.mat"), "handle_gt.mat: variable 'GT' is a function handle"),
    "import: a checkpoint .pth": (("import", "{w}/evil.pth", "--out", "{out}"), "evil.pth"),
    "extract: backbone weights .pth": (("extract", "{w}/imgs", "--descriptor", "resnet18", "--weights", "{w}/evil.pth", "--out", "{out}/d.npz"), "evil.pth"),
    "extract: a torch.export encoder .pt2": (("extract", "{w}/imgs", "--descriptor", "torchscript:{w}/evil.pt2", "--out", "{out}/d.npz"), "evil.pt2"),
    "localize: a localiser state .npz": (("localize", "--map", "{w}/map", *Q, "--resume-state", "{w}/evil_state.npz", "--out", "{out}"), "evil_state.npz"),
    "match: a map's descriptors.npy": (("match", "--map", "{w}/map_desc", *Q, "--radius", "10m"), "descriptors.npy"),
    "match: a map's segments.npy": (("match", "--map", "{w}/map_seg", *Q, "--radius", "10m"), "segments.npy"),
    "localize: a map's descriptors.npy": (("localize", "--map", "{w}/map_desc", *Q, "--out", "{out}"), "descriptors.npy"),
    "localize: query descriptors .npy": (("localize", "--map", "{w}/map", "-q", "{w}/evil.npy", "--out", "{out}"), "evil.npy"),
    "map build: descriptors .npy": (("map", "build", "{w}/evil.npy", "--out", "{out}"), "evil.npy"),
    "map build: traversal .npz": (("map", "build", "{w}/evil_trav.npz", "--out", "{out}"), "evil_trav.npz"),
    # --- named through a dataset description
    "match: description naming descriptors .npy": (("match", "-r", "{w}/desc.toml", "-q", "{w}/desc.toml"), "evil.npy"),
    "match: description naming a traversal .npz": (("match", "-r", "{w}/trav.toml", "-q", "{w}/trav.toml"), "evil_trav.npz"),
    "match: description naming a .npz with a pickled member": (("match", "-r", "{w}/member.toml", "-q", "{w}/member.toml"), "evil_member.npz"),
    "match: description naming ground truth .npy": (("match", "-r", "{w}/gt_npy.toml", "-q", "{w}/gt_npy.toml"), "evil_gt.npy"),
    "match: description naming ground truth .npz": (("match", "-r", "{w}/gt_npz.toml", "-q", "{w}/gt_npz.toml", "--gt-layout", "ref-query"), "evil_gt.npz"),
    "match: description naming descriptors .mat": (("match", "-r", "{w}/mat.toml", "-q", "{w}/mat.toml"), "handle.mat: variable 'Y'"),
    "match: description naming ground truth .mat": (("match", "-r", "{w}/gt_mat.toml", "-q", "{w}/gt_mat.toml"), "handle_gt.mat: variable 'GT'"),
    "map build: description naming descriptors .npy": (("map", "build", "{w}/desc.toml", "--out", "{out}"), "evil.npy"),
    "localize: description naming descriptors .npy": (("localize", "--map", "{w}/map", "-q", "{w}/desc.toml", "--out", "{out}"), "evil.npy"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_pickle_is_one_line_naming_the_file_and_never_runs(world, tmp_path, monkeypatch, capsys, case):
    args, fragment = CASES[case]
    out = tmp_path / "out"
    run_bad_case(monkeypatch, capsys, args, fragment, world, out)
    assert not (world / "PWNED").exists(), "the payload ran"


def recall(monkeypatch, capsys, out, reference, query) -> dict:
    code, text, err = run_cli(monkeypatch, capsys, "match", "-r", reference, "-q", query, "--radius", "2f", "-L", 3,
                              "--json", "--out", out)
    assert code == 0, err
    return json.loads(text)["recall"]


def test_big_endian_descriptors_match_as_native(world, tmp_path, monkeypatch, capsys):
    for side in ("ref", "qry"):
        values = np.load(world / f"{side}.npz")["descriptors"]
        np.save(tmp_path / f"{side}.npy", values)
        np.save(tmp_path / f"{side}_be.npy", values.astype(values.dtype.newbyteorder(">")))
    native = recall(monkeypatch, capsys, tmp_path / "a", tmp_path / "ref.npy", tmp_path / "qry.npy")
    big = recall(monkeypatch, capsys, tmp_path / "b", tmp_path / "ref_be.npy", tmp_path / "qry_be.npy")
    assert big == native and any(v > 0 for v in native.values())

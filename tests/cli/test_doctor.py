"""``seqvpr doctor`` reports what a bug report needs."""

from __future__ import annotations

import json

from tests.helpers import run_cli


def test_doctor_names_versions_devices_simd_threads_and_caches(tmp_path, monkeypatch, capsys):
    (tmp_path / "cache").mkdir()
    (tmp_path / "cache" / "entry.npz").write_bytes(b"x" * 2048)
    code, out, err = run_cli(monkeypatch, capsys, "doctor", "--cache-dir", tmp_path / "cache", "--json")
    assert code == 0, err
    report = json.loads(out)
    assert report["versions"]["torch"].startswith("2.") and report["versions"]["seqvpr"]
    assert report["devices"]["cuda available"] in (True, False)
    assert report["compute"]["numba threading layer"] in ("omp", "tbb", "workqueue")
    assert "faiss SIMD" in report["compute"]
    assert "(1 files" in report["caches"]["descriptor cache"]


def test_doctor_lists_seqvprs_cache_folders(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("SEQVPR_CACHE", str(tmp_path / "c"))
    (tmp_path / "c" / "bag-frames" / "ab").mkdir(parents=True)
    (tmp_path / "c" / "bag-frames" / "ab" / "ab12.jpg").write_bytes(b"x" * 1024)
    code, out, err = run_cli(monkeypatch, capsys, "doctor", "--json")
    assert code == 0, err
    caches = json.loads(out)["caches"]
    assert caches["cache"].startswith(f"{tmp_path / 'c'} (1 files")
    assert caches["bag frames"].startswith(f"{tmp_path / 'c' / 'bag-frames'} (1 files")
    monkeypatch.setenv("SEQVPR_BAG_FRAMES", str(tmp_path / "frames"))
    code, out, err = run_cli(monkeypatch, capsys, "doctor", "--json")
    assert json.loads(out)["caches"]["bag frames"] == f"{tmp_path / 'frames'} (none yet)"

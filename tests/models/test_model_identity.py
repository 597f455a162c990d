"""A model folder proves what it holds: config.json, written last, records its version and the weights' digest;
loading checks them, so weights and a config of different runs are refused, and folders from before still load."""

from __future__ import annotations

import json
import warnings

import torch

from seqvpr.identity import digest_file
from seqvpr.maps.index import model_record
from seqvpr.models.files import CONFIG_FILE, MODEL_FILE, MODEL_VERSION
from seqvpr.models.registry import load_trained_model
from seqvpr.models.seqnet import save_seqnet
from seqvpr.sequences.descriptors import SeqNet
from tests.helpers import raises_one_line


def test_the_config_records_the_weights_digest_and_loading_checks_it(tmp_path):
    save_seqnet(tmp_path / "a", SeqNet(6, 5, 2), {})
    save_seqnet(tmp_path / "b", SeqNet(6, 5, 2), {})
    config = json.loads((tmp_path / "a" / CONFIG_FILE).read_text())
    assert config["version"] == MODEL_VERSION
    assert config["files"] == {MODEL_FILE: digest_file(tmp_path / "a" / MODEL_FILE)}
    (tmp_path / "a" / MODEL_FILE).write_bytes((tmp_path / "b" / MODEL_FILE).read_bytes())  # same shapes, other run
    message = raises_one_line("its content is not what", load_trained_model, tmp_path / "a")
    assert str(tmp_path / "a" / MODEL_FILE) in message and CONFIG_FILE in message


def test_a_folder_from_before_the_digest_loads_without_a_word(tmp_path):
    model = SeqNet(6, 5, 2)
    save_seqnet(tmp_path / "old", model, {})
    config = json.loads((tmp_path / "old" / CONFIG_FILE).read_text())
    del config["version"], config["files"]
    (tmp_path / "old" / CONFIG_FILE).write_text(json.dumps(config))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loaded = load_trained_model(tmp_path / "old")
    assert all(torch.equal(loaded.module.state_dict()[k], v) for k, v in model.state_dict().items())


def test_a_config_naming_files_outside_the_folder_or_of_another_version_is_one_line(tmp_path):
    save_seqnet(tmp_path / "m", SeqNet(6, 5, 2), {})
    path = tmp_path / "m" / CONFIG_FILE
    config = json.loads(path.read_text())
    path.write_text(json.dumps({**config, "files": {"../elsewhere": "sha256:00"}}))
    raises_one_line("not a file of the folder", load_trained_model, tmp_path / "m")
    path.write_text(json.dumps({**config, "files": "model.safetensors"}))
    raises_one_line("'files' must map file names to digests", load_trained_model, tmp_path / "m")
    path.write_text(json.dumps({**config, "version": 2}))
    raises_one_line("model folder version 2 is not known", load_trained_model, tmp_path / "m")


def test_a_maps_model_record_is_the_weights_identity(tmp_path):
    save_seqnet(tmp_path / "m", SeqNet(6, 5, 2), {})
    recorded = json.loads((tmp_path / "m" / CONFIG_FILE).read_text())["files"][MODEL_FILE]
    assert model_record(tmp_path / "m") == {"folder": str(tmp_path / "m"), "sha256": recorded.split(":", 1)[1]}

"""NetVLAD and PCA-whitening against plain formulas."""

import numpy as np
import pytest
import torch

from seqvpr.features.pooling import NetVLAD
from seqvpr.features.whitening import fit_pca_whitening
from tests.helpers import raises_one_line


def test_netvlad_matches_the_plain_formula():
    torch.manual_seed(0)
    layer = NetVLAD(clusters=3, dim=4)
    features = torch.randn(2, 4, 2, 3)
    out = layer(features).detach().numpy()
    w = layer.assign.weight.detach()[:, :, 0, 0].numpy()
    b = layer.assign.bias.detach().numpy()
    c = layer.centroids.detach().numpy()
    for batch in range(2):
        local = features[batch].reshape(4, -1).T.numpy()
        local = local / np.linalg.norm(local, axis=1, keepdims=True)
        vlad = np.zeros((3, 4))
        for x in local:
            logits = w @ x + b
            a = np.exp(logits - logits.max())
            a /= a.sum()
            for k in range(3):
                vlad[k] += a[k] * (x - c[k])
        vlad /= np.linalg.norm(vlad, axis=1, keepdims=True)
        flat = vlad.ravel() / np.linalg.norm(vlad.ravel())
        assert np.allclose(out[batch], flat, atol=1e-5)


def test_netvlad_kmeans_init_places_centroids_on_clusters_and_is_seeded():
    rng = np.random.default_rng(0)
    centres = np.eye(6)[:3] * 1.0
    local = np.concatenate([c + 0.05 * rng.normal(size=(50, 6)) for c in centres])
    layer = NetVLAD(clusters=3, dim=6)
    layer.init_from_features(torch.from_numpy(local), seed=1)
    found = layer.centroids.detach().numpy()
    for c in centres:  # each true centre has a centroid right next to it
        assert np.max(found @ c) > 0.98
    again = NetVLAD(clusters=3, dim=6)
    again.init_from_features(torch.from_numpy(local), seed=1)
    assert torch.equal(layer.centroids, again.centroids)
    assert layer.alpha > 0
    # hard assignment of a clean centre goes to its own cluster
    soft = layer.assign(torch.from_numpy(centres).float()[:, :, None, None]).softmax(1)[:, :, 0, 0]
    assert (soft.max(1).values > 0.9).all()
    raises_one_line("at least 3 local features", NetVLAD(3, 6).init_from_features, torch.ones(2, 6))


def test_pca_whitening_whitens_the_reference_and_matches_numpy_eig():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(200, 5)) @ rng.normal(size=(5, 5)) + 3.0
    pca = fit_pca_whitening(x, 3)
    projected = ((x - x.mean(0)) @ pca.components.T) * pca.scale
    assert np.allclose(np.cov(projected.T), np.eye(3), atol=1e-6)
    values, vectors = np.linalg.eigh(np.cov(x.T))
    top = vectors[:, ::-1][:, :3].T
    assert np.allclose(np.abs(np.sum(top * pca.components, axis=1)), 1.0, atol=1e-6)
    assert np.allclose(np.linalg.norm(pca.apply(x), axis=1), 1.0, atol=1e-5)


@pytest.mark.parametrize("dim", [0, 6, 300])
def test_pca_whitening_rejects_impossible_dimensions(dim):
    raises_one_line("PCA-whitening to", fit_pca_whitening, np.ones((10, 5)), dim)


def test_pca_whitening_rejects_other_input_dimension():
    pca = fit_pca_whitening(np.random.default_rng(0).normal(size=(10, 5)), 2)
    raises_one_line("fitted on 5-D", pca.apply, np.ones((3, 4)))


def test_whiten_pair_fits_on_the_reference_only_and_caps_the_dimension():
    from seqvpr.data.traversal import Traversal
    from seqvpr.features.describe import whiten_pair

    rng = np.random.default_rng(5)
    ref = Traversal.from_descriptors(rng.normal(size=(12, 20)).astype(np.float32), name="r")
    qry = Traversal.from_descriptors(rng.normal(size=(7, 20)).astype(np.float32), name="q")
    white_ref, white_qry, used = whiten_pair(ref, qry, 4096)
    assert used == 11
    fitted = fit_pca_whitening(ref.descriptors, 11)
    assert np.allclose(white_qry.descriptors, fitted.apply(qry.descriptors), atol=1e-6)
    assert np.allclose(white_ref.descriptors, fitted.apply(ref.descriptors), atol=1e-6)

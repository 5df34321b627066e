"""Input pipeline: batches are pure functions of (seed, step); buckets; augmentation."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from conftest import icosphere, tetrahedron

from dmd_jax import pipeline
from dmd_jax.config import NoiseConfig
from dmd_jax.graph import sizes_for_vertices
from dmd_jax.mesh import canonical_frame


@pytest.fixture(scope="module")
def examples():
    meshes = [icosphere(1), icosphere(2), tetrahedron(), icosphere(1)]
    return pipeline.make_examples(meshes)


def test_batch_indices_cover_each_epoch_once():
    n, bs = 7, 3
    idx = np.concatenate([pipeline.batch_indices(s, n, bs, seed=5) for s in range(7)])
    # 21 positions = exactly 3 epochs, each a permutation of range(n).
    for epoch in range(3):
        assert sorted(idx[epoch * n : (epoch + 1) * n]) == list(range(n))
    assert not np.array_equal(idx[:n], idx[n : 2 * n])  # reshuffled per epoch


def test_batch_indices_reject_empty():
    with pytest.raises(ValueError, match="empty"):
        pipeline.batch_indices(0, 0, 2, seed=0)


def test_training_batch_is_pure_in_seed_and_step(examples):
    noise = NoiseConfig()
    a = pipeline.training_batch(examples, 3, batch_size=2, seed=11, noise=noise)
    b = pipeline.training_batch(examples, 3, batch_size=2, seed=11, noise=noise)
    c = pipeline.training_batch(examples, 4, batch_size=2, seed=11, noise=noise)
    np.testing.assert_array_equal(a.noisy, b.noisy)
    np.testing.assert_array_equal(a.clean, b.clean)
    for x, y in zip(a.graph, b.graph, strict=True):
        np.testing.assert_array_equal(x, y)
    assert a.noisy.shape != c.noisy.shape or not np.array_equal(a.noisy, c.noisy)


def test_batch_padding_and_masks(examples):
    stacked = pipeline.training_batch(examples, 0, batch_size=3, seed=0, noise=NoiseConfig())
    # One group (one device): the batch is that group on a leading axis of 1.
    assert stacked.noisy.shape[0] == 1
    batch = jax.tree.map(lambda x: x[0], stacked)
    g = batch.graph
    n_real = int(g.n_vertex_per_graph.sum())
    assert g.n_graph == 4  # three meshes + the padding graph
    assert g.vertex_mask.sum() == n_real
    assert np.all(batch.noisy[~g.vertex_mask] == 0)
    assert np.all(np.isfinite(batch.noisy))
    # Every padded size derives from the vertex bucket: one program per bucket.
    sizes = sizes_for_vertices(n_real, 0, 0, 0, 3)
    assert g.n_vertex == sizes.n_vertex
    assert g.n_face == sizes.n_face
    assert g.vertex_senders.shape[0] == sizes.n_vertex_edge
    assert g.face_senders.shape[0] == sizes.n_face_edge


def test_sizes_grow_when_edges_do_not_fit():
    small = sizes_for_vertices(100, 100, 100, 100, 1)
    big = sizes_for_vertices(100, 100, 100 * 50, 100, 1)
    assert big.n_vertex > small.n_vertex
    assert big.n_vertex_edge >= 100 * 50


def test_random_rotation_is_proper_orthogonal():
    for i in range(20):
        r = pipeline.random_rotation(jax.random.PRNGKey(i))
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0)


def test_corrupt_uses_the_noisy_canonical_frame():
    v, f = icosphere(2, radius=7.0)
    v = v + np.array([3.0, -2.0, 1.0])
    noisy, clean, spec = pipeline.corrupt(
        jax.random.PRNGKey(3), v, f, rotate=True, noise=NoiseConfig()
    )
    frame = canonical_frame(noisy)
    np.testing.assert_allclose(frame.centre, 0.0, atol=1e-12)
    assert frame.scale == pytest.approx(1.0)
    assert spec.kind in pipeline.noise_lib.NOISE_KINDS
    # Rotation keeps the clean shape's edge lengths up to the common scale.
    e_clean = np.linalg.norm(clean[f[:, 0]] - clean[f[:, 1]], axis=1)
    e_orig = np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1)
    ratio = e_clean / e_orig
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-9)


def test_evaluation_batches_fixed(examples):
    noise = NoiseConfig()
    a = pipeline.evaluation_batches(examples[:2], seed=1, noise=noise)
    b = pipeline.evaluation_batches(examples[:2], seed=1, noise=noise)
    assert len(a) == 2
    for (ba, sa), (bb, sb) in zip(a, b, strict=True):
        np.testing.assert_array_equal(ba.noisy, bb.noisy)
        assert sa == sb
        assert ba.graph.n_graph == 2

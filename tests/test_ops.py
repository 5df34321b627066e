"""The graph ops of `dmd_jax.ops` against dense (or scipy.sparse) matrix formulas.

The reference matrices are built here from the faces alone, independently of
`build_mesh_graph`: with the vertex-face incidence `B = A_FV` (`[n_face, n_vertex]`,
one 1 per face corner),

* two vertices are adjacent iff they share an edge iff some face holds both:
  `A_V = [B^T B > 0] - I`;
* two faces are adjacent iff they share an edge iff they share two vertices (in a
  triangle every vertex pair is an edge): `A_F = [B B^T >= 2] - I`. On a non-manifold
  edge this makes every pair of its faces adjacent, as the paper's `A_F` does.

Then the paper's formulas (appendix A): AGG `D̂^-1/2 Â D̂^-1/2 X W` with `Â = A + I`,
P2D `(1/3) A_FV X`, D2P `D_VF^-1 A_VF X`, DAP `mean_i |p_i - d|`, FAP per-graph mean.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp
from conftest import icosphere, shared_mesh_path, tetrahedron
from jax.test_util import check_grads

from dmd_jax import ops
from dmd_jax.graph import batch_mesh_graphs, build_mesh_graph, pad_mesh_graph, padded_sizes_for
from dmd_jax.io import load_mesh


def assert_close_f32_weights(actual, expected):
    """Edge weights are stored as float32, so aggregation agrees with a float64 reference
    to float32 precision relative to the size of the summands, not of each result."""
    scale = np.abs(expected).max()
    np.testing.assert_allclose(actual, expected, rtol=2e-6, atol=2e-6 * scale)


# --------------------------------------------------------------------------------------
# Independent references
# --------------------------------------------------------------------------------------


def incidence(faces, n_vertex):
    """`A_FV` as a scipy CSR matrix `[n_face, n_vertex]`."""
    f = np.asarray(faces)
    rows = np.repeat(np.arange(f.shape[0]), 3)
    return sp.csr_matrix((np.ones(f.size), (rows, f.ravel())), shape=(f.shape[0], n_vertex))


def primal_adjacency(faces, n_vertex):
    """`A_V` (no self loops) as scipy CSR, from `B^T B`."""
    b = incidence(faces, n_vertex)
    a = (b.T @ b).tocsr()
    a.data[:] = 1.0
    a.setdiag(0.0)
    a.eliminate_zeros()
    return a


def dual_adjacency(faces, n_vertex):
    """`A_F` (no self loops) as scipy CSR: faces sharing two vertices share an edge."""
    b = incidence(faces, n_vertex)
    shared = (b @ b.T).tocsr()
    shared.data = (shared.data >= 2).astype(np.float64)
    shared.setdiag(0.0)
    shared.eliminate_zeros()
    return shared


def gcn_matrix(adjacency):
    """`D̂^-1/2 (A + I) D̂^-1/2` as scipy CSR."""
    a_hat = adjacency + sp.identity(adjacency.shape[0], format="csr")
    d = np.asarray(a_hat.sum(axis=1)).ravel()
    inv_sqrt = sp.diags(1.0 / np.sqrt(d))
    return (inv_sqrt @ a_hat @ inv_sqrt).tocsr()


def p2d_reference(faces, n_vertex, x):
    return (incidence(faces, n_vertex) @ x) / 3.0


def d2p_reference(faces, n_vertex, x_face):
    a_vf = incidence(faces, n_vertex).T.tocsr()
    degree = np.asarray(a_vf.sum(axis=1)).ravel()
    out = a_vf @ x_face
    # D_VF^-1 is undefined for vertices in no face; the op's convention is zeros there.
    return np.where(degree[:, None] > 0, out / np.maximum(degree, 1)[:, None], 0.0)


def dap_reference(faces, p, d):
    out = np.zeros_like(d)
    for i, face in enumerate(np.asarray(faces)):
        out[i] = sum(np.abs(p[v] - d[i]) for v in face) / 3.0
    return out


def fap_reference(x, graph_id, n_graph, mask=None):
    mask = np.ones(len(x), bool) if mask is None else np.asarray(mask)
    out = np.zeros((n_graph, x.shape[1]))
    for g in range(n_graph):
        rows = x[(graph_id == g) & mask]
        if len(rows):
            out[g] = rows.mean(axis=0)
    return out


# --------------------------------------------------------------------------------------
# Meshes
# --------------------------------------------------------------------------------------


def _fandisk():
    return load_mesh(shared_mesh_path("fandisk.off"))


MESHES = {
    "tetrahedron": tetrahedron,
    "icosphere": lambda: icosphere(2),
    "fandisk": _fandisk,
}


@pytest.fixture(params=sorted(MESHES), scope="module")
def mesh(request):
    v, f = MESHES[request.param]()
    return request.param, v, f, build_mesh_graph(f, v.shape[0])


def maybe_jit(fn, use_jit, **kwargs):
    return jax.jit(fn, **kwargs) if use_jit else fn


# --------------------------------------------------------------------------------------
# Each op equals its dense formula
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("use_jit", [False, True], ids=["eager", "jit"])
def test_primal_aggregate_matches_dense_formula(mesh, use_jit):
    _, v, f, graph = mesh
    rng = np.random.default_rng(0)
    x = rng.normal(size=(v.shape[0], 5))
    w = rng.normal(size=(5, 4))
    expected = gcn_matrix(primal_adjacency(f, v.shape[0])) @ x @ w
    agg = maybe_jit(lambda g, x: ops.primal_aggregate(g, x) @ w, use_jit)
    assert_close_f32_weights(agg(graph, jnp.asarray(x)), expected)


@pytest.mark.parametrize("use_jit", [False, True], ids=["eager", "jit"])
def test_dual_aggregate_matches_dense_formula(mesh, use_jit):
    _, v, f, graph = mesh
    rng = np.random.default_rng(1)
    x = rng.normal(size=(f.shape[0], 3))
    w = rng.normal(size=(3, 6))
    expected = gcn_matrix(dual_adjacency(f, v.shape[0])) @ x @ w
    agg = maybe_jit(lambda g, x: ops.dual_aggregate(g, x) @ w, use_jit)
    assert_close_f32_weights(agg(graph, jnp.asarray(x)), expected)


def test_gcn_aggregate_dense_on_tetrahedron_by_hand():
    # Every vertex of a tetrahedron sees all four (self loop included): D̂ = 4 I, so
    # D̂^-1/2 Â D̂^-1/2 is the all-quarters matrix and every row becomes the mean.
    v, f = tetrahedron()
    graph = build_mesh_graph(f, 4)
    out = ops.primal_aggregate(graph, jnp.asarray(v))
    np.testing.assert_allclose(out, np.tile(v.mean(axis=0), (4, 1)), atol=1e-7)


@pytest.mark.parametrize("use_jit", [False, True], ids=["eager", "jit"])
def test_primal_to_dual_matches_dense_formula(mesh, use_jit):
    _, v, f, graph = mesh
    x = np.random.default_rng(2).normal(size=(v.shape[0], 4))
    p2d = maybe_jit(ops.primal_to_dual, use_jit)
    np.testing.assert_allclose(
        p2d(jnp.asarray(x), graph.faces), p2d_reference(f, v.shape[0], x), rtol=1e-12, atol=1e-12
    )


@pytest.mark.parametrize("use_jit", [False, True], ids=["eager", "jit"])
def test_dual_to_primal_matches_dense_formula(mesh, use_jit):
    _, v, f, graph = mesh
    x = np.random.default_rng(3).normal(size=(f.shape[0], 4))
    d2p = maybe_jit(ops.dual_to_primal, use_jit)
    out = d2p(jnp.asarray(x), graph.faces, graph.vertex_face_degree)
    np.testing.assert_allclose(out, d2p_reference(f, v.shape[0], x), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("use_jit", [False, True], ids=["eager", "jit"])
def test_dual_average_pool_matches_formula(mesh, use_jit):
    name, v, f, graph = mesh
    rng = np.random.default_rng(4)
    p = rng.normal(size=(v.shape[0], 3))
    d = rng.normal(size=(f.shape[0], 3))
    if name == "fandisk":  # the loop reference is slow on 14k faces; check a subset
        f_check = slice(0, 500)
    else:
        f_check = slice(None)
    dap = maybe_jit(ops.dual_average_pool, use_jit)
    out = np.asarray(dap(jnp.asarray(p), jnp.asarray(d), graph.faces))
    np.testing.assert_allclose(
        out[f_check], dap_reference(f[f_check], p, d[f_check]), rtol=1e-12, atol=1e-12
    )


@pytest.mark.parametrize("use_jit", [False, True], ids=["eager", "jit"])
def test_feature_average_pool_matches_formula(use_jit):
    rng = np.random.default_rng(5)
    x = rng.normal(size=(20, 3))
    graph_id = np.array([0] * 7 + [1] * 4 + [2] * 9, np.int32)
    mask = np.ones(20, bool)
    mask[[3, 12, 19]] = False
    fap = maybe_jit(ops.feature_average_pool, use_jit, static_argnums=2)
    np.testing.assert_allclose(
        fap(jnp.asarray(x), graph_id, 3), fap_reference(x, graph_id, 3), rtol=1e-12
    )
    np.testing.assert_allclose(
        fap(jnp.asarray(x), graph_id, 4, jnp.asarray(mask)),
        fap_reference(x, graph_id, 4, mask),  # graph 3 is empty: zeros
        rtol=1e-12,
    )


def test_fap_of_one_mesh_is_the_plain_mean(mesh):
    _, v, _, graph = mesh
    out = ops.feature_average_pool(jnp.asarray(v), graph.vertex_graph, 1, graph.vertex_mask)
    np.testing.assert_allclose(out[0], v.mean(axis=0), rtol=1e-12, atol=1e-12)


def test_broadcast_to_vertices():
    graph_features = jnp.arange(6.0).reshape(3, 2)
    out = ops.broadcast_to_vertices(graph_features, np.array([2, 0, 0, 1]))
    np.testing.assert_array_equal(out, [[4, 5], [0, 1], [0, 1], [2, 3]])


# --------------------------------------------------------------------------------------
# Gradients
# --------------------------------------------------------------------------------------


def test_ops_gradients_float64():
    v, f = icosphere(0)
    graph = build_mesh_graph(f, v.shape[0])
    rng = np.random.default_rng(6)
    x = jnp.asarray(rng.normal(size=(v.shape[0], 3)))
    y = jnp.asarray(rng.normal(size=(f.shape[0], 3)))
    assert x.dtype == jnp.float64

    # The ops are linear in the features (except DAP), so order 1 says everything there;
    # jit keeps the many numerical evaluations cheap.
    linear = {
        "primal": (lambda x: ops.primal_aggregate(graph, x), x),
        "dual": (lambda y: ops.dual_aggregate(graph, y), y),
        "p2d": (lambda x: ops.primal_to_dual(x, graph.faces), x),
        "d2p": (lambda y: ops.dual_to_primal(y, graph.faces, graph.vertex_face_degree), y),
        "fap": (lambda x: ops.feature_average_pool(x, graph.vertex_graph, 1), x),
    }
    for fn, arg in linear.values():
        check_grads(jax.jit(fn), (arg,), order=1, modes=("fwd", "rev"))
    # |p - d| is smooth away from p = d, which random features never hit.
    dap = jax.jit(lambda x, y: ops.dual_average_pool(x, y, graph.faces))
    check_grads(dap, (x, y), order=2, modes=("fwd", "rev"))


# --------------------------------------------------------------------------------------
# Node feature collision (appendix B)
# --------------------------------------------------------------------------------------


def test_node_feature_collision_and_residual_fix():
    v, f = tetrahedron()
    graph = build_mesh_graph(f, 4)
    rng = np.random.default_rng(7)
    x = jnp.asarray(rng.normal(size=(4, 8)))
    weights = [jnp.asarray(rng.normal(size=(8, 8))) for _ in range(3)]

    def agg(x, w):
        return jax.nn.relu(ops.primal_aggregate(graph, x) @ w)

    plain = x
    for w in weights:
        plain = agg(plain, w)
    # All four vertices of a tetrahedron have the same closed neighbourhood, so the
    # plain cascade maps them to one point.
    np.testing.assert_allclose(plain, np.tile(plain[0], (4, 1)), atol=1e-6)

    residual = x
    for w in weights:
        residual = agg(residual, w) + residual
    # g gives every vertex the same row, so the residual keeps the input's differences.
    diff = np.asarray(residual[:, None, :] - residual[None, :, :])
    np.testing.assert_allclose(diff, np.asarray(x[:, None, :] - x[None, :, :]), atol=1e-5)
    dist = np.linalg.norm(diff, axis=-1)
    assert dist[~np.eye(4, dtype=bool)].min() > 1e-3


# --------------------------------------------------------------------------------------
# Batching and padding
# --------------------------------------------------------------------------------------


def _three_meshes():
    tet_v, tet_f = tetrahedron()
    ico_v, ico_f = icosphere(1)
    # An open strip with a non-manifold fin and an isolated vertex: the awkward cases.
    strip_v = np.array(
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0.5, 0.5, 1], [2, 2, 2]], np.float64
    )
    strip_f = np.array([[0, 1, 2], [1, 3, 2], [1, 2, 4]], np.int32)
    return [(tet_v, tet_f), (ico_v, ico_f), (strip_v, strip_f)]


def test_batched_padded_ops_equal_per_mesh_ops():
    meshes = _three_meshes()
    graphs = [build_mesh_graph(f, v.shape[0]) for v, f in meshes]
    batch = batch_mesh_graphs(graphs)
    sizes = padded_sizes_for(batch)
    padded = pad_mesh_graph(batch, sizes)
    assert padded.n_vertex > batch.n_vertex and padded.n_face > batch.n_face
    assert padded.n_graph == 4

    rng = np.random.default_rng(8)
    xs = [rng.normal(size=(v.shape[0], 3)) for v, _ in meshes]
    ys = [rng.normal(size=(f.shape[0], 3)) for _, f in meshes]
    # Padding rows hold large values: any leak into real rows would show.
    x_all = np.concatenate(xs + [np.full((padded.n_vertex - batch.n_vertex, 3), 1e3)])
    y_all = np.concatenate(ys + [np.full((padded.n_face - batch.n_face, 3), 1e3)])

    @jax.jit
    def run(g, x, y):
        return {
            "primal": ops.primal_aggregate(g, x),
            "dual": ops.dual_aggregate(g, y),
            "p2d": ops.primal_to_dual(x, g.faces),
            "d2p": ops.dual_to_primal(y, g.faces, g.vertex_face_degree),
            "dap": ops.dual_average_pool(x, y, g.faces),
        }

    out = run(padded, jnp.asarray(x_all), jnp.asarray(y_all))
    fap = ops.feature_average_pool(
        jnp.asarray(x_all), padded.vertex_graph, padded.n_graph, padded.vertex_mask
    )
    vo = fo = 0
    for i, ((v, f), g, x, y) in enumerate(zip(meshes, graphs, xs, ys, strict=True)):
        alone = run(g, jnp.asarray(x), jnp.asarray(y))
        nv, nf = v.shape[0], f.shape[0]
        for name in ("primal", "d2p"):
            np.testing.assert_allclose(
                out[name][vo : vo + nv], alone[name], rtol=1e-12, err_msg=name
            )
        for name in ("dual", "p2d", "dap"):
            np.testing.assert_allclose(
                out[name][fo : fo + nf], alone[name], rtol=1e-12, err_msg=name
            )
        np.testing.assert_allclose(fap[i], x.mean(axis=0), rtol=1e-12)
        vo, fo = vo + nv, fo + nf
    # The padding graph has no real vertex: FAP gives it zeros, whatever padding holds.
    np.testing.assert_array_equal(fap[3], 0.0)


def test_padding_is_masked_and_weightless():
    meshes = _three_meshes()
    batch = batch_mesh_graphs([build_mesh_graph(f, v.shape[0]) for v, f in meshes])
    padded = pad_mesh_graph(batch, padded_sizes_for(batch))
    nv, nf = batch.n_vertex, batch.n_face
    assert padded.vertex_mask[:nv].all() and not padded.vertex_mask[nv:].any()
    assert padded.face_mask[:nf].all() and not padded.face_mask[nf:].any()
    ne, nfe = batch.vertex_senders.shape[0], batch.face_senders.shape[0]
    np.testing.assert_array_equal(padded.vertex_edge_weight[ne:], 0.0)
    np.testing.assert_array_equal(padded.face_edge_weight[nfe:], 0.0)
    # Padding edges touch padding nodes only.
    assert (padded.vertex_senders[ne:] >= nv).all() and (padded.vertex_receivers[ne:] >= nv).all()
    assert (padded.face_senders[nfe:] >= nf).all() and (padded.face_receivers[nfe:] >= nf).all()
    assert np.all(np.diff(padded.vertex_receivers) >= 0)
    assert np.all(np.diff(padded.face_receivers) >= 0)
    assert (padded.faces[nf:] >= nv).all()
    np.testing.assert_array_equal(padded.n_vertex_per_graph, [4, 42, 6, 0])
    np.testing.assert_array_equal(padded.n_face_per_graph, [4, 80, 3, 0])

    # D2P gives padding vertices zeros (they have no real incident face), so padding
    # features cannot grow layer after layer.
    y = jnp.full((padded.n_face, 2), 7.0)
    out = ops.dual_to_primal(y, padded.faces, padded.vertex_face_degree)
    np.testing.assert_array_equal(out[nv:], 0.0)
    # FAP with the mask ignores padding rows entirely.
    x = np.random.default_rng(9).normal(size=(padded.n_vertex, 2))
    x_changed = x.copy()
    x_changed[nv:] = 1e6
    a = ops.feature_average_pool(jnp.asarray(x), padded.vertex_graph, 4, padded.vertex_mask)
    b = ops.feature_average_pool(jnp.asarray(x_changed), padded.vertex_graph, 4, padded.vertex_mask)
    np.testing.assert_array_equal(a, b)

# %% [markdown]
# # 01 · Graph operations: the `MeshGraph` and the paper's layers
#
# DMD-Net (appendix A of the paper) is written with dense matrices: the normalised
# adjacency $\hat D^{-1/2}\hat A\hat D^{-1/2}$ of the aggregator (AGG), the vertex-face
# incidence $A_{VF}$ of primal-to-dual (P2D) and dual-to-primal (D2P), and so on. At
# 50 000 vertices a dense float32 $n\times n$ matrix is 10 GB, so `dmd_jax` never builds
# one: a mesh travels as a `MeshGraph`, a tuple of index arrays built once on the host,
# and every layer is a gather plus a `jax.ops.segment_sum`.
#
# This notebook builds the `MeshGraph` of a tetrahedron and of a generated CAD part,
# runs each layer of `dmd_jax.ops` step by step, and checks it against the paper's
# dense formula built *from the faces alone* (so the check does not reuse the index
# arrays it is checking). Every comparison prints the largest absolute difference.

# %%
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

from dmd_jax import ops
from dmd_jax.data import generate_shape
from dmd_jax.graph import (
    batch_mesh_graphs,
    build_mesh_graph,
    pad_mesh_graph,
    pad_vertex_array,
    padded_sizes_for,
)

# float64, so the differences below measure the formulas rather than float32 rounding.
jax.config.update("jax_enable_x64", True)

np.set_printoptions(precision=4, suppress=True, linewidth=100)

# %% [markdown]
# ## The tetrahedron's `MeshGraph`
#
# Four vertices, four faces, every vertex adjacent to every other. The `MeshGraph`
# stores, for the primal (vertex) graph and the dual (face) graph separately, the edges
# of $\hat A = A + I$ in both directions (self loops included), sorted by receiver, with
# the symmetric GCN weight $1/\sqrt{\hat d_s \hat d_r}$ of each edge. The remaining
# fields say which graph of a batch each vertex and face belongs to and which rows are
# padding (one mesh here: graph 0, no padding).

# %%
tet_v = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float) / 2
tet_f = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]], np.int32)
tet = build_mesh_graph(tet_f, n_vertex=4)

for name, value in tet._asdict().items():
    if value is None:  # the ELL tables, built for inference (end of this notebook)
        print(f"{name:20s} None")
        continue
    print(f"{name:20s} {str(value.dtype):8s} {str(value.shape):8s}", value.ravel()[:16])
# The claims of the next paragraph, checked.
assert np.all(tet.vertex_edge_weight == 0.25) and len(tet.vertex_edge_weight) == 16
assert np.all(tet.face_edge_weight == 0.25)

# %% [markdown]
# Every vertex of the tetrahedron has three neighbours plus its self loop, so
# $\hat d = 4$ everywhere and all 16 primal weights are $1/\sqrt{4\cdot 4} = 0.25$. Its
# dual graph is again a tetrahedron (each face shares an edge with the three others),
# so the dual weights are 0.25 as well.
#
# ## The dense reference matrices
#
# Built from the faces only, as the paper defines them:
#
# * $A_{VF}$ ($n\times f$): vertex $v$ lies on face $j$;
# * $A_V$: two vertices are adjacent when they lie on a common triangle
#   ($A_{VF}A_{VF}^\top > 0$ off the diagonal);
# * $A_F$: two faces are adjacent when they share two vertices, i.e. an edge
#   ($A_{VF}^\top A_{VF} = 2$);
# * $N = \hat D^{-1/2}(A + I)\hat D^{-1/2}$ for both graphs;
# * $D_{VF}$: the number of faces at each vertex.


# %%
def dense_operators(faces, n_vertex):
    """The paper's dense matrices, from the faces alone (no MeshGraph involved)."""
    n_face = len(faces)
    a_vf = np.zeros((n_vertex, n_face))
    a_vf[faces.T, np.arange(n_face)] = 1.0
    a_v = (a_vf @ a_vf.T > 0).astype(float)
    np.fill_diagonal(a_v, 0.0)
    a_f = (a_vf.T @ a_vf == 2).astype(float)

    def gcn(a):
        a_hat = a + np.eye(len(a))
        d = a_hat.sum(axis=1)
        return a_hat / np.sqrt(np.outer(d, d))

    return {"A_VF": a_vf, "N_V": gcn(a_v), "N_F": gcn(a_f), "D_VF": a_vf.sum(axis=1)}


tet_dense = dense_operators(tet_f, 4)
print("N_V =\n", tet_dense["N_V"])
print("A_VF =\n", tet_dense["A_VF"])

# %% [markdown]
# ## AGG's aggregation: `gcn_aggregate`
#
# `gcn_aggregate(X, senders, receivers, w)` computes $\sum_{s\to r} w_{sr} X_s$ for every
# receiver $r$: a gather of the sender rows, a multiply, and a sorted segment sum. It is
# $\hat D^{-1/2}\hat A\hat D^{-1/2}X$ without ever forming the matrix (AGG then applies
# its weight $W$, bias and ReLU; see notebook 02). `primal_aggregate` and
# `dual_aggregate` pick the vertex or face edge lists of a `MeshGraph`.
#
# On the tetrahedron, $N_V$ is $\tfrac14$ everywhere, so every output row is the mean
# of all four input rows; the vertex positions average to the origin.

# %%
x_v = tet_v  # vertex features: the positions, [4, 3]
agg = ops.primal_aggregate(tet, x_v)
print("primal_aggregate(X_V) =\n", agg)
print("max |segment sum - N_V X_V| =", np.abs(agg - tet_dense["N_V"] @ x_v).max())
assert np.abs(agg - tet_dense["N_V"] @ x_v).max() < 1e-12
assert np.abs(agg).max() < 1e-12  # every row: the mean of the four positions, the origin

# %% [markdown]
# ## P2D: primal to dual
#
# Each face gets the mean of its three vertex features, $X_F = \tfrac13 A_{FV} X_V$
# with $A_{FV} = A_{VF}^\top$. Fed positions, P2D returns the face centroids.

# %%
x_f = ops.primal_to_dual(x_v, tet.faces)
print("P2D(X_V) = face centroids =\n", x_f)
print("max |P2D - A_FV X_V / 3| =", np.abs(x_f - tet_dense["A_VF"].T @ x_v / 3).max())
assert np.abs(x_f - tet_dense["A_VF"].T @ x_v / 3).max() < 1e-12

# %% [markdown]
# ## D2P: dual to primal
#
# Each vertex gets the mean of the features of the faces around it,
# $X_V = D_{VF}^{-1}A_{VF}X_F$. The implementation scatters each face's feature to its
# three corners (`segment_sum`) and divides by `vertex_face_degree`, the diagonal of
# $D_{VF}$. Applied to the centroids, every tetrahedron vertex gets the mean of the
# three centroids around it: $\tfrac13$ of its own position, pulled towards the
# middle.

# %%
back = ops.dual_to_primal(x_f, tet.faces, tet.vertex_face_degree)
print("vertex_face_degree =", tet.vertex_face_degree)
print("D2P(P2D(X_V)) =\n", back)
reference = (tet_dense["A_VF"] @ x_f) / tet_dense["D_VF"][:, None]
print("max |D2P - D_VF^-1 A_VF X_F| =", np.abs(back - reference).max())
assert np.abs(back - reference).max() < 1e-12

# %% [markdown]
# ## DAP: dual average pooling
#
# DAP fuses a primal feature matrix $P$ ($n\times k$) with a dual one $D$
# ($f\times k$): for face $i$ with corners $a, b, c$ it averages the element-wise
# distances $|p_a - d_i|$, $|p_b - d_i|$, $|p_c - d_i|$. The reference below is the
# paper's definition as a loop over faces. With the positions and the centroids, DAP
# gives the mean per-axis distance of a face's corners from its centroid.


# %%
def dap_reference(p, d, faces):
    """Appendix A, literally: a loop over faces."""
    out = np.zeros_like(d)
    for i, corners in enumerate(faces):
        out[i] = np.mean([np.abs(p[c] - d[i]) for c in corners], axis=0)
    return out


fused = ops.dual_average_pool(x_v, x_f, tet.faces)
print("DAP(X_V, X_F) =\n", fused)
print("max |DAP - loop| =", np.abs(fused - dap_reference(x_v, x_f, tet_f)).max())
assert np.abs(fused - dap_reference(x_v, x_f, tet_f)).max() < 1e-12

# %% [markdown]
# PDF, the fusion step of a two-stream network, is DAP followed by D2P, which brings the
# fused face features back to the vertices (`dmd_jax.model.TwoStream` also adds the
# primal stream's output, a choice the model documents).
#
# ## FAP: feature average pooling, per mesh of a batch
#
# A batch is a disjoint union of meshes: `batch_mesh_graphs` offsets the indices and
# numbers the graphs, and `pad_mesh_graph` pads the union to bucketed sizes so each
# shape compiles once. Padding rows belong to an extra last graph and are `False` in
# `vertex_mask`. FAP averages the vertex features of each graph, $z = \tfrac1n\sum_i
# h_i$, leaving padding out.

# %%
cube_v = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
    float,
)
cube_f = np.array(
    [
        [0, 2, 1],
        [0, 3, 2],
        [4, 5, 6],
        [4, 6, 7],
        [0, 1, 5],
        [0, 5, 4],
        [1, 2, 6],
        [1, 6, 5],
        [2, 3, 7],
        [2, 7, 6],
        [3, 0, 4],
        [3, 4, 7],
    ],
    np.int32,
)
batch = batch_mesh_graphs([tet, build_mesh_graph(cube_f, 8)])
padded = pad_mesh_graph(batch, padded_sizes_for(batch))
x = pad_vertex_array(np.concatenate([tet_v, cube_v]), padded.n_vertex, value=99.0)
print("padded sizes: vertices", padded.n_vertex, "faces", padded.n_face, "graphs", padded.n_graph)
print("vertices per graph id:", np.bincount(padded.vertex_graph))

pooled = ops.feature_average_pool(x, padded.vertex_graph, padded.n_graph, padded.vertex_mask)
print("FAP =\n", pooled)
print(
    "max |FAP - per-mesh means| =",
    np.abs(pooled[:2] - np.stack([tet_v.mean(0), cube_v.mean(0)])).max(),
)
assert np.abs(pooled[:2] - np.stack([tet_v.mean(0), cube_v.mean(0)])).max() < 1e-12
assert np.all(np.asarray(pooled[2]) == 0)  # the padding graph, although its rows hold 99

# %% [markdown]
# The third row is the padding graph: its vertices are masked out, so it pools to zeros
# even though the padding rows were filled with 99. `broadcast_to_vertices` sends a
# per-graph result (FAP's output, or the transformer's $W_{tf}$) back to the vertices of
# each graph.
#
# Aggregation on the padded union is the block-diagonal operator: each mesh only sees
# itself, and padding edges have weight 0.

# %%
agg_batch = ops.primal_aggregate(padded, x)
agg_cube = dense_operators(cube_f, 8)["N_V"] @ cube_v
print(
    "max |batched aggregation - per-mesh dense| =",
    max(
        np.abs(agg_batch[:4] - tet_dense["N_V"] @ tet_v).max(),
        np.abs(agg_batch[4:12] - agg_cube).max(),
    ),
)
print("padding rows after aggregation:", np.unique(agg_batch[12:]))
assert np.abs(agg_batch[:4] - tet_dense["N_V"] @ tet_v).max() < 1e-12
assert np.abs(agg_batch[4:12] - agg_cube).max() < 1e-6  # float32 weights (see below)
assert np.all(np.asarray(agg_batch[12:]) == 0)

# %% [markdown]
# ## A real mesh
#
# A procedural CAD part from `dmd_jax.data` (a bracket, remeshed to a few hundred
# vertices). Vertex valences vary, so the primal weights are no longer all equal; on a
# closed manifold mesh every face has exactly three edge-neighbours, so every dual
# weight is $\tfrac14$.

# %%
v, f = generate_shape("bracket", seed=0, instance=0, min_vertices=400, max_vertices=800)
g = build_mesh_graph(f, len(v))
n_edge = (g.vertex_senders != g.vertex_receivers).sum() // 2
euler = len(v) - n_edge + len(f)
print(
    f"{len(v)} vertices, {n_edge} edges, {len(f)} faces: "
    f"Euler characteristic {euler}, genus {(2 - euler) // 2}"
)
w = g.vertex_edge_weight
print(f"primal edge weights: min {w.min():.4f} max {w.max():.4f}")
print("distinct dual edge weights:", np.unique(g.face_edge_weight))
assert np.all(g.face_edge_weight == 0.25) and w.min() < w.max()

# %%
dense = dense_operators(f, len(v))
rng = np.random.default_rng(0)
xv = rng.normal(size=(len(v), 16))  # random vertex features, k = 16
xf = rng.normal(size=(len(f), 16))  # random face features

checks = {
    "gcn_aggregate, primal": (ops.primal_aggregate(g, xv), dense["N_V"] @ xv),
    "gcn_aggregate, dual": (ops.dual_aggregate(g, xf), dense["N_F"] @ xf),
    "P2D": (ops.primal_to_dual(xv, g.faces), dense["A_VF"].T @ xv / 3),
    "D2P": (
        ops.dual_to_primal(xf, g.faces, g.vertex_face_degree),
        dense["A_VF"] @ xf / dense["D_VF"][:, None],
    ),
    "DAP": (ops.dual_average_pool(xv, xf, g.faces), dap_reference(xv, xf, f)),
    "FAP": (ops.feature_average_pool(xv, g.vertex_graph, 1), xv.mean(0, keepdims=True)),
}
differences = {}
for name, (ours, reference) in checks.items():
    differences[name] = np.abs(np.asarray(ours) - reference).max()
    print(f"{name:24s} max abs difference {differences[name]:.2e}")
assert all(d < 1e-13 for name, d in differences.items() if name != "gcn_aggregate, primal")
assert 1e-9 < differences["gcn_aggregate, primal"] < 1e-6

# %% [markdown]
# P2D, D2P, DAP, FAP and the dual aggregation agree to float64 rounding (below
# $10^{-13}$). The primal aggregation differs by about $10^{-8}$ to $10^{-7}$ (between
# $10^{-9}$ and $10^{-6}$, asserted):
# `MeshGraph` stores the edge weights $1/\sqrt{\hat d_s\hat d_r}$ in float32 (they feed
# float32 models), so each weight carries a relative error below $6\cdot10^{-8}$. The
# weights $\tfrac14$ of the tetrahedron and of this closed mesh's dual graph are exact
# in float32, hence no difference there.
#
# ## Why index arrays
#
# The dense $N_V$ of this small mesh is almost all zeros. The primal edge lists hold
# about $7n$ entries (each vertex has about six neighbours plus its self loop) and the
# dual ones about $4f \approx 8n$, so memory and work grow linearly with the mesh. The
# estimate below scales this mesh's whole `MeshGraph` (every index array) per vertex.

# %%
n = len(v)
print(
    f"dense N_V: {n} x {n} = {n * n} entries, {np.count_nonzero(dense['N_V'])} non-zero "
    f"({100 * np.count_nonzero(dense['N_V']) / n**2:.2f} %)"
)
print(
    f"MeshGraph primal edges: {len(g.vertex_senders)} ({len(g.vertex_senders) / n:.2f} per vertex)"
)
graph_bytes_per_vertex = sum(a.nbytes for a in jax.tree.leaves(g)) / n
print(f"MeshGraph: {graph_bytes_per_vertex:.0f} bytes per vertex")
assert 6 < len(g.vertex_senders) / n < 8 and 7 < len(g.face_senders) / n < 9
assert np.count_nonzero(dense["N_V"]) / n**2 < 0.05
for n_big in (50_000, 1_000_000):
    print(
        f"at {n_big:>9,d} vertices: one dense float32 matrix {4 * n_big**2 / 1e9:7.1f} GB, "
        f"the MeshGraph about {graph_bytes_per_vertex * n_big / 1e6:5.1f} MB"
    )

valence = np.bincount(g.vertex_receivers) - 1  # minus the self loop
fig, axes = plt.subplots(1, 2, figsize=(8, 3.2))
axes[0].spy(dense["N_V"], markersize=0.3)
axes[0].set_title("non-zeros of $N_V$", fontsize=10)
axes[1].hist(valence, bins=np.arange(valence.min(), valence.max() + 2) - 0.5, color="tab:blue")
axes[1].set_xlabel("vertex valence")
axes[1].set_ylabel("vertices")
axes[1].set_title("valences of the bracket", fontsize=10)
fig.tight_layout()
plt.show()

# %% [markdown]
# The non-zeros hug the diagonal because the remesher numbers neighbouring vertices
# close to each other; nothing in the layers depends on that order.
#
# Every function above is a pure JAX function of arrays, so it jits with the index
# arrays passed as arguments (closing over them makes XLA constant-fold the graph).

# %%
aggregate = jax.jit(ops.primal_aggregate)
graph_arrays = jax.tree.map(jnp.asarray, g)
print("jit == eager:", np.allclose(aggregate(graph_arrays, xv), ops.primal_aggregate(g, xv)))
assert np.allclose(aggregate(graph_arrays, xv), ops.primal_aggregate(g, xv))

# %% [markdown]
# ## The inference layout: padded neighbour tables
#
# A segment sum is a scatter, which XLA runs serially on CPU. For inference, `denoise`
# turns each edge list into an ELL table once per mesh (`mesh.with_ell_layout`): row
# $i$ lists the senders into node $i$, one per column, padded with zero-weight self
# slots to a multiple of 4, and `ops.gcn_aggregate_ell` sums one gather per column.
# It is the same operator (training keeps the edge lists); on the tetrahedron every row
# has exactly four entries:

# %%
from dmd_jax.graph import with_ell_layout

ell = with_ell_layout(tet).vertex_ell
print("neighbours\n", ell.neighbours, "\nweights\n", ell.weights)
x = np.arange(12, dtype=np.float32).reshape(4, 3)
by_table = ops.gcn_aggregate_ell(jnp.asarray(x), *ell)
by_edges = ops.primal_aggregate(tet, jnp.asarray(x))
print("table == edge lists:", np.allclose(by_table, by_edges))
assert ell.neighbours.shape == (4, 4) and np.allclose(by_table, by_edges)

big = with_ell_layout(g)  # the bracket: width = largest valence + 1, rounded up
print("bracket tables:", big.vertex_ell.neighbours.shape, big.face_ell.neighbours.shape)

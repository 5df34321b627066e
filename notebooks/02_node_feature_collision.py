# %% [markdown]
# # 02 · Node feature collision, and why every AGG is residual
#
# An aggregator (AGG) computes $g(X) = \mathrm{ReLU}(NXW + b)$ with the normalised
# adjacency $N = \hat D^{-1/2}(A+I)\hat D^{-1/2}$. Appendix B of the paper points out a
# failure of a plain cascade $g(g(g(X)))$: when two vertices have *identical* rows in
# $\hat A$ (the same neighbours, self included), $N$ gives them identical rows, so they
# leave the layer with the same feature whatever $W$ is, and no later layer can tell
# them apart. On a tetrahedron all four vertices are like that. The paper's fix is a
# residual connection, $h(X) = g(X) + X$.
#
# This notebook shows the collapse with the project's `Aggregator` module, shows that
# the residual keeps the vertices apart, and looks at what the same operator does on an
# ordinary mesh, where exact collisions are rare but $N$ still damps most of what tells
# neighbours apart.

# %%
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

from dmd_jax.data import generate_shape
from dmd_jax.graph import build_mesh_graph
from dmd_jax.model import Aggregator

np.set_printoptions(precision=4, suppress=True, linewidth=100)


def dense_n(senders, receivers, weight, n):
    """The operator a MeshGraph's edge list stands for, as a dense matrix (small n only)."""
    out = np.zeros((n, n))
    np.add.at(out, (np.asarray(receivers), np.asarray(senders)), np.asarray(weight, float))
    return out


# %% [markdown]
# ## The tetrahedron: one operator row for all four vertices

# %%
tet_v = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], np.float32) / 2
tet_f = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]], np.int32)
tet = jax.tree.map(jnp.asarray, build_mesh_graph(tet_f, 4))
edges = (tet.vertex_senders, tet.vertex_receivers, tet.vertex_edge_weight)
print("N =\n", dense_n(*edges, 4))
assert np.allclose(dense_n(*edges, 4), 0.25)

# %% [markdown]
# Every row of $N$ is $(\tfrac14, \tfrac14, \tfrac14, \tfrac14)$, so $NX$ replaces each
# vertex feature by the mean of all four.
#
# ## Three plain AGG layers versus three residual ones
#
# The input features are the vertex positions lifted to 8 channels by a fixed random
# matrix, so the four rows are distinct. Both cascades use the *same* three sets of
# weights (`Aggregator(8, residual=False)` and `Aggregator(8, residual=True)` have the
# same parameters); only the skip connection differs. After each layer we print the
# largest distance between two vertices' features.

# %%
width, n_layers = 8, 3
x0 = jnp.asarray(tet_v @ np.random.default_rng(0).normal(size=(3, width)), jnp.float32)
plain, residual = Aggregator(width, residual=False), Aggregator(width, residual=True)
params = [plain.init(jax.random.PRNGKey(i), x0, *edges) for i in range(n_layers)]


def cascade(layer, x):
    outs = [x]
    for p in params:
        outs.append(layer.apply(p, outs[-1], *edges))
    return [np.asarray(o) for o in outs]


def max_pairwise(x):
    return np.linalg.norm(x[:, None] - x[None], axis=-1).max()


plain_outs, residual_outs = cascade(plain, x0), cascade(residual, x0)
print("layer   plain: max distance   residual: max distance")
for k, (p, r) in enumerate(zip(plain_outs, residual_outs, strict=True)):
    print(f"{k:5d}   {max_pairwise(p):20.3e}   {max_pairwise(r):23.3e}")
# The next paragraph's claims: plain collapses at layer 1 and stays collapsed; residual
# keeps at least the input's spread.
assert max_pairwise(plain_outs[0]) > 0.5
assert all(max_pairwise(o) < 1e-5 for o in plain_outs[1:])
assert all(max_pairwise(o) > 0.99 * max_pairwise(x0) for o in residual_outs)

# %% [markdown]
# After the first plain layer the four vertices are one point (the distance is 0, or
# float32 rounding of the sums), and they stay one point: layers 2 and 3 only move that
# point. The residual cascade keeps the input's spread, and more than that: since $g$
# gives all four vertices the same row $c$, $h_i - h_j = (c + x_i) - (c + x_j) = x_i -
# x_j$, so the pairwise differences survive every layer, exactly up to float32
# rounding of the sums.

# %%
for k, out in enumerate(residual_outs):
    diff = (out[:, None] - out[None]) - (residual_outs[0][:, None] - residual_outs[0][None])
    print(f"layer {k}: max |(h_i - h_j) - (x_i - x_j)| = {np.abs(diff).max():.1e}")
    assert np.abs(diff).max() < 1e-4 * max(1.0, np.abs(out).max())  # float32 rounding

# %% [markdown]
# The same picture, projected onto the two leading principal directions of the input
# (one fixed projection for every panel):

# %%
centred = residual_outs[0] - residual_outs[0].mean(0)
basis = np.linalg.svd(centred, full_matrices=False)[2][:2].T  # [width, 2]
colours = ["tab:blue", "tab:orange", "tab:green", "tab:red"]
fig, axes = plt.subplots(2, n_layers + 1, figsize=(9, 4.4), sharex="row", sharey="row")
for row, (name, outs) in enumerate([("plain", plain_outs), ("residual", residual_outs)]):
    for k, out in enumerate(outs):
        xy = (out - out.mean(0)) @ basis  # centred per panel: the shift c is not the point
        ax = axes[row, k]
        ax.scatter(xy[:, 0], xy[:, 1], c=colours, s=40)
        ax.set_title(f"{name}, layer {k}", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
fig.tight_layout()
plt.show()

# %% [markdown]
# Top row: the four coloured vertices fall onto one dot from layer 1 on. Bottom row:
# the residual cascade keeps the tetrahedron's shape in feature space.
#
# ## The dual graph of a tetrahedron collapses too
#
# The four faces of a tetrahedron are pairwise adjacent, so its dual graph is again the
# complete graph on four nodes, and a plain dual AGG merges the four face features the
# same way.

# %%
face_edges = (tet.face_senders, tet.face_receivers, tet.face_edge_weight)
x_faces = jnp.asarray(np.random.default_rng(1).normal(size=(4, width)), jnp.float32)
p = plain.init(jax.random.PRNGKey(7), x_faces, *face_edges)
after_plain = max_pairwise(np.asarray(plain.apply(p, x_faces, *face_edges)))
after_residual = max_pairwise(np.asarray(residual.apply(p, x_faces, *face_edges)))
print(
    f"max distance between faces: input {max_pairwise(np.asarray(x_faces)):.3f}, "
    f"after one plain dual AGG {after_plain:.1e}, after one residual {after_residual:.3f}"
)
assert after_plain < 1e-5 and after_residual > 0.5 * max_pairwise(np.asarray(x_faces))

# %% [markdown]
# ## Which vertices collide exactly?
#
# Two nodes leave a plain AGG with the same feature for *every* input exactly when their
# rows of $\hat A$ are equal: the same closed neighbourhood $\{i\} \cup
# \mathcal{N}(i)$. (Equal rows of $\hat A$ give equal degrees, hence equal rows of $N$.)
# The helper below groups nodes by their closed neighbourhood. Besides the tetrahedron,
# the simplest case is an open quad of two triangles: the two ends of the diagonal see
# exactly the same four vertices.


# %%
def colliding_groups(senders, receivers, n_node):
    """Groups of nodes (size > 1) with identical closed neighbourhoods in the edge list."""
    neighbourhoods = [[] for _ in range(n_node)]
    for s, r in zip(np.asarray(senders), np.asarray(receivers), strict=True):
        neighbourhoods[r].append(int(s))
    groups = {}
    for node, nbrs in enumerate(neighbourhoods):
        groups.setdefault(tuple(sorted(nbrs)), []).append(node)
    return [g for g in groups.values() if len(g) > 1]


quad = build_mesh_graph(np.array([[0, 1, 2], [0, 2, 3]]), 4)
print("tetrahedron vertices:", colliding_groups(tet.vertex_senders, tet.vertex_receivers, 4))
print("tetrahedron faces:   ", colliding_groups(tet.face_senders, tet.face_receivers, 4))
print("quad vertices:       ", colliding_groups(quad.vertex_senders, quad.vertex_receivers, 4))
assert colliding_groups(tet.vertex_senders, tet.vertex_receivers, 4) == [[0, 1, 2, 3]]
assert colliding_groups(tet.face_senders, tet.face_receivers, 4) == [[0, 1, 2, 3]]
assert colliding_groups(quad.vertex_senders, quad.vertex_receivers, 4) == [[0, 2]]

# %% [markdown]
# On the procedural meshes of `dmd_jax.data` (remeshed, closed or open), exact
# collisions do not occur at all:

# %%
for category in ("bracket", "blob", "torus", "terrain"):
    v, f = generate_shape(category, seed=0, instance=0, min_vertices=400, max_vertices=800)
    g = build_mesh_graph(f, len(v))
    nv = len(colliding_groups(g.vertex_senders, g.vertex_receivers, len(v)))
    nf = len(colliding_groups(g.face_senders, g.face_receivers, len(f)))
    print(
        f"{category:8s} {len(v):4d} vertices: "
        f"{nv} colliding vertex groups, {nf} colliding face groups"
    )
    assert nv == nf == 0, category

# %% [markdown]
# ## The wider picture: $N$ is a low-pass filter
#
# Exact collisions need identical neighbourhoods, but the mechanism behind them acts on
# every mesh. $N$ is symmetric, so it has an orthonormal eigenbasis $u_k$ with
# eigenvalues $\lambda_k \in (-1, 1]$; the constant-per-component direction (scaled by
# $\sqrt{\hat d}$) has $\lambda = 1$, and directions that vary quickly between
# neighbours have $|\lambda|$ near 0. Without the ReLU, a plain layer maps the component
# of $X$ along $u_k$ to $\lambda_k\,(u_k^\top X)\,W$: $W$ mixes channels, it cannot undo
# the factor $\lambda_k$. Three plain layers multiply it by $\lambda_k^3$. A residual
# layer maps it to $(u_k^\top X)(\lambda_k W + I)$, which keeps a $\lambda = 0$ component
# intact.
#
# The tetrahedron is the extreme case: $N = \tfrac14\mathbf{1}\mathbf{1}^\top$ has
# eigenvalues $1, 0, 0, 0$, so one plain layer removes everything but the mean. On the
# bracket:

# %%
v, f = generate_shape("bracket", seed=0, instance=0, min_vertices=400, max_vertices=800)
g = build_mesh_graph(f, len(v))
lam = np.linalg.eigvalsh(
    dense_n(g.vertex_senders, g.vertex_receivers, g.vertex_edge_weight, len(v))
)
print("tetrahedron eigenvalues:", np.linalg.eigvalsh(dense_n(*edges, 4)))
print(
    f"bracket: {len(lam)} eigenvalues in [{lam.min():.3f}, {lam.max():.3f}], "
    f"median |λ| = {np.median(np.abs(lam)):.3f}"
)
print(
    f"share of directions damped below 1 % by three linear plain layers (|λ|³ < 0.01): "
    f"{np.mean(np.abs(lam) ** 3 < 0.01):.0%}"
)
assert np.allclose(np.linalg.eigvalsh(dense_n(*edges, 4)), [0, 0, 0, 1], atol=1e-6)
assert -1 < lam.min() and abs(lam.max() - 1) < 1e-5
# "Most eigenvalues are small": the median |λ| is below 1/2.
assert np.median(np.abs(lam)) < 0.5

fig, axes = plt.subplots(1, 2, figsize=(8, 2.8))
axes[0].hist(lam, bins=50, color="tab:blue")
axes[0].set_xlabel("eigenvalue λ of N (bracket)")
axes[0].set_ylabel("count")
grid = np.linspace(lam.min(), 1, 200)
for k in (1, 2, 3):
    axes[1].plot(grid, np.abs(grid) ** k, label=f"{k} plain layer{'s' if k > 1 else ''}")
axes[1].set_xlabel("λ")
axes[1].set_ylabel("gain |λ|^k")
axes[1].legend(fontsize=8)
fig.tight_layout()
plt.show()

# %% [markdown]
# Most eigenvalues of the bracket's $N$ are small (left), and the gain of a plain
# cascade on them falls off quickly with depth (right): after three linear plain layers,
# the printed share of the directions keeps less than 1 % of its amplitude. These are
# exactly the directions that distinguish a vertex from its neighbours, the detail a
# denoiser has to see. The ReLU between layers mixes frequencies, so this is the picture
# for the linear part only, but it shows why the residual matters beyond the
# tetrahedron.
#
# In `dmd_jax.model`, every AGG of the two-stream networks is residual (each stream
# starts with a linear projection to the stream width so that all three can be), and
# the transformer's densely connected AGGs receive the concatenation of every earlier
# output, which carries the input forward the same way.

"""DMD-Net in Flax: aggregators, two-stream networks, feature extractor, transformer,
denoiser, and every structure-ablation variant, switched by a `ModelConfig`.

All graph work goes through `dmd_jax.ops` (gather + segment sum over the index arrays of
a `MeshGraph`, or the padded-neighbour gather of its ELL layouts when the graph carries
them, as inference's does); no dense adjacency matrix is built. A batch is a padded
disjoint union of meshes, so every per-mesh quantity (FAP, the transformation `W_tf`, the
STN matrix) is computed per graph id, and padding rows, which form a separate graph with
zero-weight edges, never reach a real row.

Call:

    model = DMDNet(config)
    params = model.init(key, vertices, graph)["params"]
    denoised, features, aux = model.apply({"params": params}, vertices, graph)

`vertices` are canonical-frame `[n_vertex, 3]` positions (padded like `graph`); `graph` is
a `MeshGraph` whose fields are arrays. Dropout needs `deterministic=False` and
`rngs={"dropout": key}`.

Top-level parameter collections are `feature_extractor`, `transformer`, `denoiser` and
`stn` (each present only when the variant has it), so training schemes can freeze the
feature extractor by its subtree.

Choices where the paper is silent (see docs/design-decisions.md, "Model"):

* AGG bias is added after aggregation, `ReLU(Â X W + b)`, so it is not reweighted by
  the normalised adjacency; residual `h = g(X) + X` when widths match (appendix B).
* Each stream of a two-stream network starts with a linear projection to `width`, so all
  three aggregators can be residual.
* PDF output is `D2P(DAP(p, d)) + p` (`pdf_residual=True`): DAP keeps only absolute
  differences, so without the primal skip the sign of every feature is lost after one
  two-stream network and symmetric neighbourhoods collide, the problem appendix B solves
  with residuals inside the streams.
* The feature extractor's normal part is normalised to unit length (the FE loss compares
  with unit normals, and the transformer then sees normals on the sphere).
* Transformer: FC+ReLU, `dense_layers` densely connected AGGs (each gets the
  concatenation of the FC output and every previous AGG output; no residual, the dense
  connections already carry the input), one AGG on the concatenation of all, FC to
  `in_dim * width` without ReLU, FAP per mesh, reshape to `W_tf [n_graph, in_dim, width]`;
  then `ReLU`-AGG (residual) on the transformed features.
* MT: a cascade of `mt_transforms` matrices from the same trunk, `8 x 8` then `8 x width`,
  with a ReLU between (without it the cascade collapses to one matrix).
* The denoiser gets `[transformed features ‖ noisy xyz]`; FGT variants without a
  transformer (W/O T) feed `[xyz ‖ features]`, denoiser-only variants feed xyz.
* The denoiser head starts at zero (`head_init_scale=0`), so an untrained offset model is
  the identity map; activations grow through the residual stacks (measured rms ≈ 60 at
  the denoiser's last two-stream output at init), which a random head would turn into
  offsets larger than the shape.
* STN: per-vertex MLP (`stn_width`, `2 stn_width`), FAP, FC, FC to 9 initialised to the
  identity; the network sees `xyz @ T` while the offset is added to the untransformed
  noisy positions.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import linen as nn

from dmd_jax import encoding, geometry, ops
from dmd_jax.config import ModelConfig
from dmd_jax.geometry import safe_normalize
from dmd_jax.graph import EllLayout, MeshGraph, build_mesh_graph
from dmd_jax.vertex_update import solve_vertices_to_normals

Dtype = jnp.dtype


@jax.custom_vjp
def symmetric_aggregate(x, senders, receivers, edge_weight):
    """`ops.gcn_aggregate` whose backward pass is the same sorted segment sum.

    The GCN operator `D̂^-1/2 Â D̂^-1/2` of a `MeshGraph` is symmetric: every edge is
    stored in both directions with the weight `1/sqrt(d_s d_r)`, and padding edges are
    weight-0 self loops. Its transpose is then itself, so the cotangent of `x` is one more
    aggregation with receivers sorted, instead of the scatter over unsorted senders that
    autodiff of the gather would give (about 40 % faster forward + backward on CPU).
    Edge weights are treated as constants (no gradient).

    Args:
      x: `[n_node, d]`.
      senders, receivers, edge_weight: `[n_edge]` symmetric edge lists (as built by
        `build_mesh_graph`, `batch_mesh_graphs` and `pad_mesh_graph`).

    Returns:
      `[n_node, d]`.
    """
    return ops.gcn_aggregate(x, senders, receivers, edge_weight)


def _symmetric_aggregate_fwd(x, senders, receivers, edge_weight):
    return ops.gcn_aggregate(x, senders, receivers, edge_weight), (senders, receivers, edge_weight)


def _symmetric_aggregate_bwd(residual, cotangent):
    senders, receivers, edge_weight = residual
    return ops.gcn_aggregate(cotangent, senders, receivers, edge_weight), None, None, None


symmetric_aggregate.defvjp(_symmetric_aggregate_fwd, _symmetric_aggregate_bwd)


class Aggregator(nn.Module):
    """AGG: `h = Dropout(ReLU(D̂^-1/2 Â D̂^-1/2 X W + b)) (+ X)`, on a primal or dual graph.

    With `attention=True` the fixed symmetric weights are replaced by GAT coefficients
    `α_ij = softmax_j(LeakyReLU(a_s·W x_j + a_r·W x_i))` over the same edge lists (self
    loops included); edges of weight 0 (padding) are left out of the softmax.

    Without attention, an `ell` layout of the same edges (`MeshGraph.vertex_ell` or
    `face_ell`, from `graph.with_ell_layout`) replaces the segment sum by
    `ops.gcn_aggregate_ell`: the same operator, faster on CPU (inference uses it). The
    attention path ignores `ell`; its softmax needs the edge lists.

    Attributes:
      features: output width.
      residual: add the input when its width equals `features`.
      dropout_rate: dropout after the ReLU.
      attention: GAT-style attention coefficients.
      param_dtype: dtype of the parameters.
    """

    features: int
    residual: bool = True
    dropout_rate: float = 0.0
    attention: bool = False
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(
        self,
        x,
        senders,
        receivers,
        edge_weight,
        *,
        deterministic: bool = True,
        ell: EllLayout | None = None,
    ):
        """Aggregates, transforms and activates node features.

        Args:
          x: `[n_node, d_in]` node features.
          senders, receivers: `[n_edge]` int32 edges of `A + I` (receivers sorted).
          edge_weight: `[n_edge]` GCN weights; 0 marks padding edges.
          deterministic: turn dropout off.
          ell: optional `EllLayout` of the same edges (`[n_node, width]` tables);
            used instead of the edge lists when attention is off.

        Returns:
          `[n_node, features]`.
        """
        if x.ndim != 2:
            raise ValueError(f"Aggregator expects [n_node, d] features, got {x.shape}")
        n_node, d_in = x.shape
        kernel = nn.Dense(
            self.features, use_bias=False, param_dtype=self.param_dtype, name="kernel"
        )
        bias = self.param("bias", nn.initializers.zeros, (self.features,), self.param_dtype)
        if self.attention:
            h = self._attend(kernel(x), senders, receivers, edge_weight)
        else:

            def aggregate(y):
                if ell is not None:  # the same operator as a padded table: no scatter
                    return ops.gcn_aggregate_ell(y, *ell)
                return symmetric_aggregate(y, senders, receivers, edge_weight)

            if d_in < self.features:
                # Aggregate at the narrower width: the product is linear, the order is free.
                h = kernel(aggregate(x))
            else:
                h = aggregate(kernel(x))
        h = nn.relu(h + bias.astype(h.dtype))
        h = nn.Dropout(self.dropout_rate)(h, deterministic=deterministic)
        if self.residual and d_in == self.features:
            h = h + x
        return h

    def _attend(self, xw, senders, receivers, edge_weight):
        n_node, width = xw.shape
        init = nn.initializers.normal(stddev=1.0 / np.sqrt(width))
        a_s = self.param("attn_sender", init, (width,), self.param_dtype)
        a_r = self.param("attn_receiver", init, (width,), self.param_dtype)
        score = xw @ a_s.astype(xw.dtype)
        logits = nn.leaky_relu(score[senders] + (xw @ a_r.astype(xw.dtype))[receivers], 0.2)
        valid = edge_weight > 0
        floor = jnp.finfo(logits.dtype).min
        logits = jnp.where(valid, logits, floor)
        top = jax.ops.segment_max(logits, receivers, num_segments=n_node, indices_are_sorted=True)
        # Softmax is shift invariant; the max only keeps exp in range.
        top = jax.lax.stop_gradient(jnp.where(jnp.isfinite(top), top, 0.0))
        e = jnp.where(valid, jnp.exp(jnp.where(valid, logits - top[receivers], 0.0)), 0.0)
        denom = jax.ops.segment_sum(e, receivers, num_segments=n_node, indices_are_sorted=True)
        alpha = e / jnp.where(denom > 0, denom, 1.0)[receivers]
        return jax.ops.segment_sum(
            xw[senders] * alpha[:, None], receivers, num_segments=n_node, indices_are_sorted=True
        )


class TwoStream(nn.Module):
    """Two-stream network: primal and dual AGG cascades fused by PDF; or a single stream.

    Primal stream: `Dense(width)` on `X_V`, then `n_agg` residual AGGs on the vertex graph.
    Dual stream: `Dense(width)` on `P2D(X_V)`, then `n_agg` residual AGGs on the face
    graph. PDF: `D2P(DAP(p, d))`, plus `p` when `pdf_residual`. With `two_stream=False`
    the output is the primal stream alone (no dual stream, no PDF).

    Attributes:
      width: output width.
      two_stream: use the dual stream and PDF.
      n_agg: aggregators per stream.
      dropout_rate, attention: passed to every AGG.
      pdf_residual: add the primal stream output to the fused output.
      param_dtype: dtype of the parameters.
    """

    width: int
    two_stream: bool = True
    n_agg: int = 3
    dropout_rate: float = 0.0
    attention: bool = False
    pdf_residual: bool = True
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(
        self,
        x,
        graph: MeshGraph,
        *,
        face_x=None,
        deterministic: bool = True,
        return_dual: bool = False,
    ):
        """Runs both streams and fuses them.

        Args:
          x: `[n_vertex, d_in]` primal features.
          graph: the mesh graph.
          face_x: optional `[n_face, d_face]` face features, concatenated to `P2D(x)` as
            the dual stream's input (the `"local"` encoding's face normals).
          return_dual: also return face features: the dual stream's output and its DAP
            fusion with the primal stream, `[d ‖ DAP(p, d)]`.

        Returns:
          `[n_vertex, width]` primal features; with `return_dual`, also
          `[n_face, 2 width]` face features.
        """
        agg = dict(
            dropout_rate=self.dropout_rate, attention=self.attention, param_dtype=self.param_dtype
        )
        p = nn.Dense(self.width, param_dtype=self.param_dtype, name="primal_in")(x)
        for i in range(self.n_agg):
            p = Aggregator(self.width, name=f"primal_agg{i}", **agg)(
                p,
                graph.vertex_senders,
                graph.vertex_receivers,
                graph.vertex_edge_weight,
                deterministic=deterministic,
                ell=graph.vertex_ell,
            )
        if not self.two_stream:
            if return_dual:
                raise ValueError("a single-stream network has no dual features")
            return p
        d_in = ops.primal_to_dual(x, graph.faces)
        if face_x is not None:
            d_in = jnp.concatenate([d_in, face_x.astype(d_in.dtype)], axis=-1)
        d = nn.Dense(self.width, param_dtype=self.param_dtype, name="dual_in")(d_in)
        for i in range(self.n_agg):
            d = Aggregator(self.width, name=f"dual_agg{i}", **agg)(
                d,
                graph.face_senders,
                graph.face_receivers,
                graph.face_edge_weight,
                deterministic=deterministic,
                ell=graph.face_ell,
            )
        fused = ops.dual_to_primal(
            ops.dual_average_pool(p, d, graph.faces), graph.faces, graph.vertex_face_degree
        )
        out = fused + p if self.pdf_residual else fused
        if return_dual:
            # The face-level fusion (before D2P) carries the primal stream too.
            return out, jnp.concatenate([d, ops.dual_average_pool(p, d, graph.faces)], -1)
        return out


class _Stack(nn.Module):
    """`n` two-stream networks followed by a linear head (FE and denoiser share it).

    With `out_dim=0` there is no head and the call returns `(primal [n_vertex, width],
    faces [n_face, 2 width] or None)`, the last two-stream network's outputs (see
    `TwoStream`'s `return_dual`).
    """

    config: ModelConfig
    n: int
    two_stream: bool
    out_dim: int
    head_init: nn.initializers.Initializer = nn.initializers.lecun_normal()

    @nn.compact
    def __call__(self, x, graph: MeshGraph, *, face_x=None, deterministic: bool = True):
        cfg = self.config
        d = None
        for i in range(self.n):
            last = self.out_dim == 0 and self.two_stream and i == self.n - 1
            x = TwoStream(
                cfg.width,
                two_stream=self.two_stream,
                n_agg=cfg.n_agg,
                dropout_rate=cfg.dropout,
                attention=cfg.attention,
                pdf_residual=cfg.pdf_residual,
                param_dtype=_param_dtype(cfg),
                name=f"two_stream{i}",
            )(x, graph, face_x=face_x, deterministic=deterministic, return_dual=last)
            if last:
                x, d = x
        if self.out_dim == 0:
            return x, d
        return nn.Dense(
            self.out_dim, kernel_init=self.head_init, param_dtype=_param_dtype(cfg), name="head"
        )(x)


class FeatureExtractor(nn.Module):
    """`fe_two_streams` two-stream networks and a linear head to `[n, 5]`.

    The output is `[unit normal (3) ‖ κ_H ‖ κ_G]` estimated for the clean mesh; the normal
    part is normalised when `config.normalize_fe_normals`.
    """

    config: ModelConfig

    @nn.compact
    def __call__(self, x, graph: MeshGraph, *, face_x=None, deterministic: bool = True):
        cfg = self.config
        out = _Stack(cfg, cfg.fe_two_streams, cfg.fe_two_stream, 5, name="stack")(
            x, graph, face_x=face_x, deterministic=deterministic
        )
        if cfg.normalize_fe_normals:
            out = jnp.concatenate([safe_normalize(out[:, :3]), out[:, 3:]], axis=-1)
        return out


def apply_transform(x, w, vertex_graph):
    """Per-mesh linear map: row `i` of `x` times the matrix of its mesh.

    Written as a sum over the few input columns so the `[n, in, out]` gather is never
    materialised.

    Args:
      x: `[n_vertex, a]`.
      w: `[n_graph, a, b]` one matrix per mesh.
      vertex_graph: `[n_vertex]` int32 graph id of each row.

    Returns:
      `[n_vertex, b]`.
    """
    if x.shape[1] != w.shape[1]:
        raise ValueError(f"cannot apply [{w.shape[1]}, {w.shape[2]}] maps to {x.shape} rows")
    out = x[:, 0:1] * w[vertex_graph, 0, :]
    for i in range(1, x.shape[1]):
        out = out + x[:, i : i + 1] * w[vertex_graph, i, :]
    return out


class Transformer(nn.Module):
    """Computes `W_tf` per mesh from the local features and applies it (FGT).

    Attributes:
      config: the model config (`width` is the output width, `hidden_transformer_width`
        the trunk's, `transform_in_dim` the rows of `W_tf`, `n_transforms` the cascade).
    """

    config: ModelConfig

    @nn.compact
    def __call__(
        self, features, x_in, graph: MeshGraph, *, deterministic: bool = True, pooled=None
    ):
        """Computes the per-mesh transformation(s) and applies them to `x_in`.

        Args:
          features: `[n_vertex, 5]` guidance (feature extractor output).
          x_in: `[n_vertex, in_dim]` what the transformation acts on.
          graph: the mesh graph.
          pooled: optional dict of FAP results to use instead of pooling over `graph`
            (see `DMDNet`): `"w_tf{k}"` -> `[rows * cols]` or `[n_graph, rows * cols]`.

        Returns:
          `(t [n_vertex, width], [W_tf per transformation, each [n_graph, a, b]])`.
        """
        cfg = self.config
        pd = _param_dtype(cfg)
        hidden = cfg.hidden_transformer_width
        in_dim = cfg.transform_in_dim
        if x_in.shape[1] != in_dim:
            raise ValueError(f"transformer input must have {in_dim} columns, got {x_in.shape}")
        edges = (graph.vertex_senders, graph.vertex_receivers, graph.vertex_edge_weight)
        ell = graph.vertex_ell
        agg = dict(
            dropout_rate=cfg.dropout, attention=cfg.attention, param_dtype=pd, residual=False
        )

        # One (rows x cols) matrix per transformation of the cascade, each from its own
        # FC head (no ReLU: W_tf entries must not be skewed positive) and FAP per mesh.
        shapes = [(in_dim, in_dim)] * (cfg.n_transforms - 1) + [(in_dim, cfg.width)]
        n_graph = graph.n_vertex_per_graph.shape[0]
        names = [f"w_tf{k}" for k in range(len(shapes))]
        if pooled is not None and all(name in pooled for name in names):
            # Patch-wise inference: the whole mesh's FAP, computed beforehand; the trunk
            # that feeds it is not needed here.
            mats = [
                _broadcast_pooled(pooled[name], n_graph).reshape(n_graph, rows, cols)
                for name, (rows, cols) in zip(names, shapes, strict=True)
            ]
        else:
            h = nn.relu(nn.Dense(hidden, param_dtype=pd, name="fc_in")(features))
            h = nn.Dropout(cfg.dropout)(h, deterministic=deterministic)
            outs = [h]
            for i in range(cfg.dense_layers):
                outs.append(
                    Aggregator(hidden, name=f"dense_agg{i}", **agg)(
                        jnp.concatenate(outs, axis=-1), *edges, deterministic=deterministic, ell=ell
                    )
                )
            h = Aggregator(hidden, name="agg", **agg)(
                jnp.concatenate(outs, axis=-1), *edges, deterministic=deterministic, ell=ell
            )
            # FAP of an affine head is the head of the FAP: pool the hidden features, then
            # apply each head once per mesh. Never materialises the per-vertex
            # `[n_vertex, rows * cols]` matrices (1,600 floats a vertex for `small`, the
            # largest buffer of the pooling pass); a mesh with no vertex still gets zeros.
            pooled_h = ops.feature_average_pool(h, graph.vertex_graph, n_graph, graph.vertex_mask)
            nonempty = ops.feature_average_pool(
                jnp.ones_like(h[:, :1]), graph.vertex_graph, n_graph, graph.vertex_mask
            )
            mats = []
            for k, (rows, cols) in enumerate(shapes):
                head = "fc_out" if k == len(shapes) - 1 else f"fc_cascade{k}"
                mean = nn.Dense(rows * cols, param_dtype=pd, name=head)(pooled_h) * nonempty
                # Recorded only when the caller makes "intermediates" mutable (patch-wise
                # inference sums these over patches); a no-op otherwise.
                self.sow("intermediates", names[k], mean)
                mats.append(mean.reshape(n_graph, rows, cols))

        t = x_in
        for k, w in enumerate(mats):
            t = apply_transform(t, w, graph.vertex_graph)
            if k < len(mats) - 1:
                t = nn.relu(t)
        t = Aggregator(
            cfg.width,
            name="agg_out",
            dropout_rate=cfg.dropout,
            attention=cfg.attention,
            param_dtype=pd,
        )(t, *edges, deterministic=deterministic, ell=ell)
        return t, mats


class SpatialTransformer(nn.Module):
    """PointNet-style T-Net: one 3 x 3 matrix per mesh, the identity at initialisation."""

    config: ModelConfig

    @nn.compact
    def __call__(self, xyz, graph: MeshGraph, *, deterministic: bool = True, pooled=None):
        """Returns `[n_graph, 3, 3]`.

        `pooled`, optional: a dict whose `"stn"` entry (`[2 stn_width]` or
        `[n_graph, 2 stn_width]`) replaces the FAP over `graph` (see `DMDNet`).
        """
        cfg = self.config
        pd = _param_dtype(cfg)
        n_graph = graph.n_vertex_per_graph.shape[0]
        if pooled is not None and "stn" in pooled:
            g = _broadcast_pooled(pooled["stn"], n_graph)
        else:
            h = nn.relu(nn.Dense(cfg.stn_width, param_dtype=pd, name="mlp0")(xyz))
            h = nn.relu(nn.Dense(2 * cfg.stn_width, param_dtype=pd, name="mlp1")(h))
            g = ops.feature_average_pool(h, graph.vertex_graph, n_graph, graph.vertex_mask)
            self.sow("intermediates", "stn", g)
        g = nn.relu(nn.Dense(cfg.stn_width, param_dtype=pd, name="fc0")(g))
        eye = jnp.eye(3).reshape(-1)
        flat = nn.Dense(
            9,
            kernel_init=nn.initializers.zeros,
            bias_init=lambda k, s, d: eye.astype(d),
            param_dtype=pd,
            name="fc_out",
        )(g)
        return flat.reshape(n_graph, 3, 3)


class Denoiser(nn.Module):
    """`depth` two-stream networks and a head.

    `head="offset"`: a linear head to `[n_vertex, 3]` (offset or positions).
    `head="normal"`: a linear head on the last dual stream to `[n_face, K + 3]`: mixing
    logits over the `K` candidate normals (the noisy face normal and the pre-filtered
    ones) and a correction `δ`; the face normal is `normalize(Σ_k softmax_k n_k + δ)`.
    Starting from zeros, an untrained head is the plain average of the candidates.
    (A single-stream denoiser has no dual stream: its face features are then a Dense
    of `[P2D(primal) ‖ face_x]`.)
    """

    config: ModelConfig

    @nn.compact
    def __call__(
        self, x, graph: MeshGraph, *, face_x=None, candidates=None, deterministic: bool = True
    ):
        cfg = self.config
        pd = _param_dtype(cfg)
        if cfg.head == "offset":
            if cfg.head_init_scale == 0:
                head_init = nn.initializers.zeros
            else:
                head_init = nn.initializers.variance_scaling(
                    cfg.head_init_scale, "fan_in", "normal"
                )
            return _Stack(
                cfg, cfg.depth, cfg.denoiser_two_stream, 3, head_init=head_init, name="stack"
            )(x, graph, face_x=face_x, deterministic=deterministic)
        p, d = _Stack(cfg, cfg.depth, cfg.denoiser_two_stream, 0, name="stack")(
            x, graph, face_x=face_x, deterministic=deterministic
        )
        if d is None:
            d_in = ops.primal_to_dual(p, graph.faces)
            if face_x is not None:
                d_in = jnp.concatenate([d_in, face_x.astype(d_in.dtype)], axis=-1)
            d = nn.relu(nn.Dense(cfg.width, param_dtype=pd, name="dual_out")(d_in))
        k = candidates.shape[1]
        out = nn.Dense(k + 3, kernel_init=nn.initializers.zeros, param_dtype=pd, name="head")(d)
        if cfg.head_consistency:
            extra = encoding.candidate_consistency(candidates.astype(out.dtype), graph)
            out = out + nn.Dense(
                k + 3,
                kernel_init=nn.initializers.zeros,
                use_bias=False,
                param_dtype=pd,
                name="head_consistency",
            )(extra)
        weights = jax.nn.softmax(out[:, :k], axis=-1)
        mixed = jnp.einsum("fk,fkc->fc", weights, candidates.astype(out.dtype))
        return safe_normalize(mixed + out[:, k:])


class DMDNet(nn.Module):
    """DMD-Net (FGT paradigm) and its structure-ablation variants.

    Returns `(denoised [n_vertex, 3], features [n_vertex, 5] or None, aux)` where `aux`
    holds `"w_tf"` (list of `[n_graph, a, b]`, transformer variants) and `"stn"`
    (`[n_graph, 3, 3]`, with `stn=True`).

    The only per-mesh (non-local) quantities are the feature average pools (FAP) of the
    STN (`"stn"`, `[n_graph, 2 stn_width]`) and of the transformer's heads (`"w_tf{k}"`,
    `[n_graph, rows * cols]`, one per transformation of the cascade); `pooled_names`
    lists them for a config. Called with `mutable=["intermediates"]`, the model records
    each under that name (`self.sow`); called with `pooled={name: value}`, it uses the
    given value (`[d]`, broadcast to every graph, or `[n_graph, d]`) instead of pooling
    over `graph`. Patch-wise inference (`dmd_jax.patches`) uses both: it sums the
    pools of disjoint vertex sets over the patches of a large mesh, then runs each patch
    with the whole mesh's pools, so every other operation sees only a neighbourhood.
    Without these arguments the model is unchanged.

    `local`, optional (`"local"` encoding only): the encoding's parameter-free inputs of
    `vertices` on `graph` (`encoding.LocalInputs`: vertex columns `[n_vertex, V]`,
    candidate normals `[n_face, K, 3]`), computed beforehand, e.g. once per cached noisy
    draw in training (`pipeline.CandidatePool`); the call then skips the pre-filters.
    Given exactly what `encoding.local_inputs(vertices, graph, config)` returns, the
    outputs are those of the call without it.
    """

    config: ModelConfig

    @nn.compact
    def __call__(
        self,
        vertices,
        graph: MeshGraph,
        *,
        deterministic: bool = True,
        pooled=None,
        local: encoding.LocalInputs | None = None,
    ):
        cfg = self.config
        n_vertex = graph.vertex_graph.shape[0]
        if vertices.ndim != 2 or vertices.shape != (n_vertex, 3):
            raise ValueError(
                f"vertices must have shape [n_vertex, 3] = [{n_vertex}, 3] to match the "
                f"graph, got {vertices.shape}"
            )
        xyz = jnp.asarray(vertices).astype(_param_dtype(cfg))
        aux = {}
        face_x = candidates = None
        if cfg.encoding == "local" and local is not None:
            # Computed once outside the call (`encoding.local_inputs`, the training
            # pipeline's candidate pool): they have no parameters, so the step need not
            # recompute them.
            x_in = jnp.asarray(local.vertex).astype(xyz.dtype)
            candidates = jnp.asarray(local.candidates).astype(xyz.dtype)
            face_x = candidates.reshape(candidates.shape[0], -1)
        elif cfg.encoding == "local":
            x_in, face_x, candidates = encoding.local_features(
                xyz,
                graph,
                filter_iterations=cfg.filter_iterations,
                taubin_iterations=cfg.taubin_iterations,
                filter_sigmas=cfg.filter_sigmas,
            )
        else:
            x_in = xyz
        if cfg.stn:
            # The STN acts on the three coordinate-like columns (xyz, or the Laplacian
            # coordinates of the local encoding); the offset is added to the untransformed
            # positions.
            mats = SpatialTransformer(cfg, name="stn")(
                x_in[:, :3], graph, deterministic=deterministic, pooled=pooled
            )
            aux["stn"] = mats
            x_in = jnp.concatenate(
                [apply_transform(x_in[:, :3], mats, graph.vertex_graph), x_in[:, 3:]], axis=-1
            )

        features = None
        if cfg.uses_feature_extractor:
            features = FeatureExtractor(cfg, name="feature_extractor")(
                x_in, graph, face_x=face_x, deterministic=deterministic
            )

        if cfg.uses_transformer:
            t_in = x_in if cfg.variant == "fgt3" else jnp.concatenate([x_in, features], -1)
            t, mats = Transformer(cfg, name="transformer")(
                features, t_in, graph, deterministic=deterministic, pooled=pooled
            )
            aux["w_tf"] = mats
            den_in = jnp.concatenate([t, x_in], axis=-1)
        elif cfg.uses_feature_extractor:
            den_in = jnp.concatenate([x_in, features], axis=-1)
        else:
            den_in = x_in

        out = Denoiser(cfg, name="denoiser")(
            den_in, graph, face_x=face_x, candidates=candidates, deterministic=deterministic
        )
        if cfg.head == "normal":
            aux["face_normals"] = out
            faces = graph.faces
            corner_face = jnp.repeat(jnp.arange(faces.shape[0], dtype=faces.dtype), 3)
            free = jnp.ones(xyz.shape[0], xyz.dtype)
            if cfg.vertex_update == "solve":
                denoised = solve_vertices_to_normals(
                    xyz,
                    faces,
                    out,
                    free,
                    tolerance=cfg.vertex_tolerance,
                    max_iterations=cfg.vertex_max_iterations,
                    normal_weight=cfg.vertex_normal_weight,
                    tangent_weight=cfg.vertex_tangent_weight,
                )
            else:
                denoised = geometry.fit_vertices_to_normals(
                    xyz, faces, out, faces.reshape(-1), corner_face, free, cfg.vertex_iterations
                )
        else:
            denoised = xyz + out if cfg.predict_offset else out
        return denoised, features, aux


def pooled_names(config: ModelConfig) -> tuple[tuple[str, ...], ...]:
    """The model's per-mesh pools, in the order they depend on each other.

    Returns:
      Stages of names (see `DMDNet`): `("stn",)` first when `config.stn` (the
      transformer's input depends on it), then `("w_tf0", ...)` for transformer
      variants. Each stage can be computed once the earlier ones are known.
    """
    stages = []
    if config.stn:
        stages.append(("stn",))
    if config.uses_transformer:
        stages.append(tuple(f"w_tf{k}" for k in range(config.n_transforms)))
    return tuple(stages)


def _broadcast_pooled(value, n_graph: int):
    """A given pool, `[d]` or `[n_graph, d]`, as `[n_graph, d]`."""
    value = jnp.asarray(value)
    if value.ndim == 1:
        return jnp.broadcast_to(value[None, :], (n_graph, value.shape[0]))
    if value.ndim != 2 or value.shape[0] != n_graph:
        raise ValueError(f"a pooled override must be [d] or [{n_graph}, d], got {value.shape}")
    return value


def _param_dtype(cfg: ModelConfig):
    return jnp.float64 if cfg.dtype == "float64" else jnp.float32


def _tetrahedron_graph() -> tuple[jnp.ndarray, MeshGraph]:
    v = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=np.float32) / 2
    f = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]], dtype=np.int32)
    return jnp.asarray(v), jax.tree.map(jnp.asarray, build_mesh_graph(f, 4))


def init_params(config: ModelConfig, key, vertices=None, graph: MeshGraph | None = None):
    """Initial parameters of `DMDNet(config)`; shapes do not depend on the mesh.

    Args:
      config: the model config.
      key: PRNG key.
      vertices, graph: an example input; a tetrahedron when omitted.
    """
    if graph is None:
        vertices, graph = _tetrahedron_graph()
    graph = jax.tree.map(jnp.asarray, graph)
    return DMDNet(config).init({"params": key}, jnp.asarray(vertices), graph)["params"]


def param_shapes(config: ModelConfig):
    """Parameter pytree of `jax.ShapeDtypeStruct` (via `jax.eval_shape`, no compute)."""
    vertices, graph = _tetrahedron_graph()
    return jax.eval_shape(
        lambda k: DMDNet(config).init({"params": k}, vertices, graph)["params"],
        jax.random.PRNGKey(0),
    )


def param_count(config: ModelConfig) -> int:
    """Number of learnable parameters of `DMDNet(config)`."""
    return int(sum(np.prod(x.shape) for x in jax.tree.leaves(param_shapes(config))))


def param_counts_by_module(config: ModelConfig) -> dict[str, int]:
    """Parameter count of each top-level module (`feature_extractor`, ...)."""
    shapes = param_shapes(config)
    return {
        name: int(sum(np.prod(x.shape) for x in jax.tree.leaves(sub)))
        for name, sub in shapes.items()
    }

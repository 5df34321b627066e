"""`denoise`: a noisy mesh in any frame in, denoised vertices in the same frame out.

The weights it runs come from `dmd_jax.checkpoints` (`load_pretrained`, `load_weights`,
`load_model`); the padded graph it runs on from `dmd_jax.graph`.
"""

from __future__ import annotations

from functools import lru_cache

import jax
import jax.numpy as jnp
import numpy as np

from dmd_jax.checkpoints import as_bundle
from dmd_jax.config import ExperimentConfig
from dmd_jax.encoding import mesh_frame
from dmd_jax.graph import (
    build_mesh_graph,
    pad_mesh_graph,
    pad_vertex_array,
    padded_sizes_for,
    with_ell_layout,
)
from dmd_jax.mesh import validate_mesh

AGGREGATIONS = ("auto", "ell", "segment_sum")
# `auto` keeps a graph's ELL table while it holds at most this many slots per distinct
# edge. The shared meshes, padded, need 1.8-2.9 (vertex graph) and 1.2-1.4 (face graph);
# truck.obj, with a vertex of valence 36, 6.6, where its table still beat the segment sum
# (benchmarks/README.md). A pole of valence 1000 would need hundreds.
AUTO_MAX_FILL = 8.0


@lru_cache(maxsize=8)
def _predictor(config: ExperimentConfig):
    """The jitted forward pass of a config (configs are frozen and hashable: the key)."""
    from dmd_jax.model import DMDNet

    model = DMDNet(config.model)

    @jax.jit
    def predict(params, noisy, graph):
        out, _, _ = model.apply({"params": params}, noisy, graph, deterministic=True)
        return out

    return predict


def denoise(
    vertices,
    faces,
    params,
    *,
    config: ExperimentConfig | None = None,
    iterations: int = 1,
    aggregation: str = "auto",
) -> np.ndarray:
    """Denoises a triangle mesh with a trained DMD-Net.

    The mesh is mapped to the frame of the model's encoding (`encoding.mesh_frame`:
    bounding box centred, and longest side 1 or mean edge length 1), denoised, and
    mapped back, so the result is translation- and scale-equivariant.

    Args:
      vertices: `[n_vertex, 3]` in any frame; float16/32/64 or integer.
      faces: `[n_face, 3]` integer indices.
      params: a `ModelBundle` (from `load_pretrained()`, `load_weights()` or a training
        checkpoint via `load_model`), a path for `load_model`, or raw params with
        `config`.
      config: the experiment config, needed only with raw params.
      iterations: how many times to apply the network (each pass starts from the last).
      aggregation: how the GCN aggregations run (the same operator either way, equal up
        to float summation order): `"ell"` through padded neighbour tables
        (`graph.with_ell_layout`; faster on CPU, no scatter), `"segment_sum"` over the
        edge lists, as in training, or `"auto"`: the tables of the vertex and face
        graphs, except a table padded to more than `AUTO_MAX_FILL` slots per edge (a
        vertex of very high valence), whose graph then uses its edge lists. Attention
        models use the edge lists regardless.

    Returns:
      `[n_vertex, 3]` denoised vertices in the input frame; float32 for float32 input,
      float64 otherwise.

    Raises:
      ValueError: bad mesh (see `dmd_jax.mesh.validate_mesh`), bad params, or an
        unknown `aggregation`.
    """
    if int(iterations) < 1:
        raise ValueError(f"iterations must be at least 1, got {iterations}")
    if aggregation not in AGGREGATIONS:
        raise ValueError(
            f"unknown aggregation {aggregation!r}; choose one of {', '.join(AGGREGATIONS)}"
        )
    v, f = validate_mesh(vertices, faces)
    in_dtype = np.asarray(vertices).dtype
    bundle = as_bundle(params, config)
    frame = mesh_frame(bundle.config.model.encoding, v, f)
    x = frame.apply(v)
    # The padded graph does not change between passes: build it (edge lists, ELL
    # tables) and move it to the device once, not once per pass.
    graph = build_mesh_graph(f, v.shape[0])
    graph = pad_mesh_graph(graph, padded_sizes_for(graph))
    if aggregation != "segment_sum":
        graph = with_ell_layout(graph, max_fill=AUTO_MAX_FILL if aggregation == "auto" else None)
    graph = jax.tree.map(jnp.asarray, graph)
    predict = _predictor(bundle.config)
    n, n_padded = v.shape[0], graph.n_vertex
    for _ in range(int(iterations)):
        # As training pads the noisy positions: float32, zeros on padding rows.
        noisy = pad_vertex_array(x.astype(np.float32), n_padded)
        out = predict(bundle.params, jnp.asarray(noisy), graph)
        x = np.asarray(out[:n], np.float64)
        if not np.all(np.isfinite(x)):
            raise ValueError("the network produced non-finite vertices (broken weights?)")
    result = frame.invert(x)
    return result.astype(np.float32) if in_dtype == np.float32 else result

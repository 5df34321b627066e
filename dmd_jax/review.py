"""The review: after the network, a learned look at its output beside a route's.

The learned pre-smoothing choice (`dmd_jax.presmooth`) reads only the noisy mesh, and
under light noise the noise dominates what it reads: it cannot tell a CAD part whose
flats the network blurs from an organic mesh the network denoises well (validation
split, 0.1 edges: the network ends at 6.17° on `cgal_boeing` where its own σ 0.2 field
alone ends at 3.06°). The review reads the *outputs*: the network's result and one
network-free route's (`dmd_jax.routes`) on the same noisy mesh, how far apart their face
normals are and how flat and how creased each one is (`OUTPUT_FEATURE_NAMES`); and
keeps the network's result, takes a route's, or runs a cascade (a route's field and
vertex update on the network's result: a second stage), by
the same nearest-neighbour regression as the pre-smoothing choice
(`presmooth.learned_option`), on examples of the training split
(`benchmarks/quality/review_learn.py`; policy fields `DenoisePolicy.review_*` and
`DenoisePolicy.cascade_*`).

Host side, NumPy. The route it compares runs on at most `REVIEW_MAX_FACES` faces (a
connected patch of a larger mesh, `review_crop`), so the review's cost is bounded (about
0.3 s); a route or cascade it takes then runs on the whole mesh.
"""

from __future__ import annotations

import numpy as np

from dmd_jax.mesh import face_normals_np
from dmd_jax.presmooth import _angles, _edge_pairs
from dmd_jax.routes import run_route
from dmd_jax.topology import face_adjacency

OUTPUT_FEATURE_NAMES = (
    "log mean angle network-route",
    "log median angle network-route",
    "network share under 1 deg",
    "network share over 30 deg",
    "log network median",
    "route share under 1 deg",
    "route share over 30 deg",
    "log route median",
)
# The review's route runs on at most this many faces (0.15 s at 10k faces for 60 passes).
REVIEW_MAX_FACES = 10_000


def review_crop(faces: np.ndarray, n_vertex: int, max_faces: int = REVIEW_MAX_FACES):
    """`(used, faces)`: the vertices and renumbered faces of a connected patch of the
    mesh's `max_faces` faces nearest its first face (breadth first over faces sharing an
    edge: any face order), or `(None, faces)` for a mesh of at most `max_faces` faces.
    Where the first face's component is smaller, that component (at least a face).

    A patch, not the first faces of the file: a file may list faces with no locality (a
    grid generator writing every lower triangle, then every upper one), and scattered
    faces share no edge. 80 ms at 100k faces.
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import breadth_first_order

    f = np.asarray(faces)
    if f.shape[0] <= max_faces:
        return None, f
    a, b = face_adjacency(f, n_vertex)
    adjacency = sp.csr_matrix((np.ones(a.size, np.int8), (a, b)), shape=(f.shape[0],) * 2)
    patch = breadth_first_order(adjacency, 0, directed=False, return_predecessors=False)
    used, sub = np.unique(f[np.sort(patch[:max_faces])], return_inverse=True)
    return used, sub.reshape(-1, 3)


def _neighbour_stats(normals, a, b) -> list[float]:
    angles = _angles(normals, a, b)
    if angles.size == 0:
        return [0.0, 0.0, float(np.log(0.5))]
    return [
        float(np.mean(angles < 1.0)),
        float(np.mean(angles > 30.0)),
        float(np.log(np.median(angles) + 0.5)),
    ]


def output_features(network_out, route_out, faces) -> np.ndarray:
    """What the review reads of two results on one mesh (`OUTPUT_FEATURE_NAMES`).

    Scale and rotation free: angles between their face normals (log of the mean and the
    median, + 0.5° so equal outputs stay finite), and per result the share of angles
    between edge-adjacent face normals under 1° (flats) and over 30° (creases) and the
    log of their median.

    Args:
      network_out, route_out: `[n_vertex, 3]` positions of the same mesh.
      faces: `[n_face, 3]` vertex indices.

    Returns:
      `[len(OUTPUT_FEATURE_NAMES)]` float64.
    """
    f = np.asarray(faces)
    nn = face_normals_np(np.asarray(network_out, np.float64), f)
    nr = face_normals_np(np.asarray(route_out, np.float64), f)
    ok = (np.abs(nn).sum(axis=1) > 0) & (np.abs(nr).sum(axis=1) > 0)
    between = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", nn[ok], nr[ok]), -1.0, 1.0)))
    if between.size == 0:
        between = np.zeros(1)
    a, b = _edge_pairs(f, np.asarray(network_out).shape[0])
    return np.array(
        [
            np.log(between.mean() + 0.5),
            np.log(np.median(between) + 0.5),
            *_neighbour_stats(nn, a, b),
            *_neighbour_stats(nr, a, b),
        ]
    )


def review_features(noisy, network_out, faces, sigma_r: float, passes: int) -> np.ndarray:
    """`output_features` of the network's result and the route `(sigma_r, passes)`
    (`routes.run_route` on the noisy mesh), on the mesh's first `REVIEW_MAX_FACES`
    faces (`review_crop`).

    Args:
      noisy: `[n_vertex, 3]` the noisy positions the network was given (before any
        pre-smoothing).
      network_out: `[n_vertex, 3]` the network's result.
      faces: `[n_face, 3]` vertex indices.
      sigma_r, passes: the compared route.
    """
    noisy = np.asarray(noisy, np.float64)
    network_out = np.asarray(network_out, np.float64)
    used, f = review_crop(faces, noisy.shape[0])
    if used is not None:
        noisy, network_out = noisy[used], network_out[used]
    return output_features(network_out, run_route(noisy, f, sigma_r, passes), f)


def review_choice(policy, noisy, network_out, faces) -> int:
    """The option the policy's review takes: 0 keeps the network's result, `1 + i` takes
    route `i` (`policy.route_sigmas`), `1 + n_route + j` cascade `j`
    (`policy.cascade_sigmas`; `review_result` makes the chosen positions).

    Two choices from one set of features: between the network's result and the routes
    (`review_regrets`), then, where it keeps the network's result and the policy has
    cascades, between that result and the cascades (`cascade_regrets`).

    Args:
      policy: a `DenoisePolicy` with a review (`policy.reviews`).
      noisy: `[n_vertex, 3]` the noisy positions (before any pre-smoothing).
      network_out: `[n_vertex, 3]` the network's result, in the same frame.
      faces: `[n_face, 3]` vertex indices.
    """
    from dmd_jax.presmooth import learned_option

    k = policy.review_route
    features = review_features(
        noisy, network_out, faces, policy.route_sigmas[k], policy.route_passes[k]
    )
    n_route = len(policy.route_sigmas)
    table = (policy.review_center, policy.review_scale, policy.review_examples)
    option = learned_option(
        features, 1 + n_route, *table, policy.review_regrets, policy.review_neighbours
    )
    if option or not policy.cascade_sigmas:
        return option
    cascade = learned_option(
        features,
        1 + len(policy.cascade_sigmas),
        *table,
        policy.cascade_regrets,
        policy.cascade_neighbours,
    )
    return 0 if cascade == 0 else n_route + cascade


def review_result(policy, option: int, noisy, network_out, faces) -> np.ndarray:
    """The positions of review option `option` (`review_choice`): the network's result,
    a route run on the noisy mesh, or a cascade run on the network's result.

    Args:
      policy: the `DenoisePolicy` whose options `option` indexes.
      option: 0, a route `1 + i` or a cascade `1 + n_route + j`.
      noisy, network_out: `[n_vertex, 3]` as `review_choice` takes them.
      faces: `[n_face, 3]` vertex indices.
    """
    n_route = len(policy.route_sigmas)
    if option == 0:
        return network_out
    if option <= n_route:
        i = option - 1
        return run_route(noisy, faces, policy.route_sigmas[i], policy.route_passes[i])
    j = option - 1 - n_route
    return run_route(network_out, faces, policy.cascade_sigmas[j], policy.cascade_passes[j])

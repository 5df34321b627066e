"""Procedural shape categories: the project's stand-in for ShapeNet.

Every shape is a pure function of `(category, seed, instance)`: its parameters come from
`np.random.default_rng([seed, crc32(category), instance, attempt, stream])`, so the same
triple gives the same mesh whatever process builds it, in whatever order. (Bit-identical
results additionally need the same NumPy, manifold3d and pymeshlab builds and the same CPU
floating-point paths; the dataset manifest stores a hash of every mesh so a rebuild can be
checked.)

A shape is built in three steps:

1. a *base* surface, fine enough that its facets are invisible at the final resolution:
   CSG with manifold3d (CAD parts, revolved profiles), explicit parametric grids (tubes,
   tori, height fields, star-shaped surfaces) or marching cubes of a smooth field
   (metaballs, genus-n shapes);
2. pymeshlab isotropic remeshing (`meshing_isotropic_explicit_remeshing`) to a vertex
   count drawn in `[min_vertices, max_vertices]`, with the target edge length computed from
   the area and corrected for a few rounds until the count lands in range. Edges whose
   dihedral angle exceeds the category's feature angle are kept as creases, so CAD parts
   keep their sharp edges;
3. cleaning and checking (no duplicate or unreferenced vertices, no duplicate or
   degenerate faces, one connected component, consistent winding, edge- and vertex-manifold,
   watertight and outward-oriented for closed categories). A shape that fails any check is
   redrawn with the next `attempt` number, so failures are deterministic too.

The result is centred on its bounding box and scaled so its longest side is 1. No random
rotation is applied: rotation augmentation belongs to the input pipeline.

All categories are closed (watertight, outward-oriented, genus fixed by construction where
stated) except `terrain`, which is an open height-field patch with one boundary loop:
real scans have open boundaries (lion, camel) and the network should see some.

Layout: `kit` holds the building blocks (manifold3d solids, swept tubes, marching
cubes), `cad` and `freeform` the category builders, this module the registry and
`generate_shape`; the cleaning, remeshing and checks live in `dmd_jax.data.repair`
(re-exported here).
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from dmd_jax.data.repair import (
    clean_mesh,
    decimate,
    mesh_area,
    mesh_problems,
    remesh,
)
from dmd_jax.data.shapes.cad import (
    _build_blocks,
    _build_bracket,
    _build_csg,
    _build_extrusion,
    _build_fastener,
    _build_flange,
    _build_gear,
)
from dmd_jax.data.shapes.freeform import (
    _build_blob,
    _build_bottle,
    _build_cup,
    _build_genus,
    _build_metaballs,
    _build_relief,
    _build_superquadric,
    _build_terrain,
    _build_torus,
    _build_tube,
    _build_twisted_bar,
    _build_vase,
)
from dmd_jax.data.shapes.kit import _Reject
from dmd_jax.mesh import canonical_frame

GENERATOR_VERSION = 1


class CategoryInfo(NamedTuple):
    """What a category promises.

    Attributes:
      name: category name (an entry of `CATEGORIES`).
      closed: watertight, outward-oriented surface; `False` means an open patch.
      feature_angle: dihedral angle in degrees above which remeshing keeps an edge as a
        crease (90 for categories without creases).
      genus: the genus every shape of the category has, or `None` when it varies.
      description: one line.
    """

    name: str
    closed: bool
    feature_angle: float
    genus: int | None
    description: str


class _Spec(NamedTuple):
    build: Callable[[np.random.Generator], tuple[np.ndarray, np.ndarray]]
    info: CategoryInfo


def _spec(name, build, closed, feature_angle, genus, description) -> tuple[str, _Spec]:
    return name, _Spec(build, CategoryInfo(name, closed, feature_angle, genus, description))


_SPECS: dict[str, _Spec] = dict(
    [
        _spec("blocks", _build_blocks, True, 30.0, None, "unions of boxes with pockets and holes"),
        _spec("bracket", _build_bracket, True, 30.0, None, "L-brackets with gussets, holes, slots"),
        _spec("extrusion", _build_extrusion, True, 30.0, None, "prisms of random outlines"),
        _spec("gear", _build_gear, True, 30.0, None, "spur gears with bore, hub, keyway"),
        _spec("csg", _build_csg, True, 30.0, None, "box/sphere/cylinder CSG solids"),
        _spec("fastener", _build_fastener, True, 30.0, None, "chamfered nuts and bolts"),
        _spec("flange", _build_flange, True, 30.0, None, "revolved stepped parts, bolt circles"),
        _spec("vase", _build_vase, True, 30.0, 0, "solid or hollow vases, smooth profiles"),
        _spec("cup", _build_cup, True, 30.0, None, "thick-walled cups, with or without handle"),
        _spec("bottle", _build_bottle, True, 30.0, 0, "closed bottles with shoulder and neck"),
        _spec("blob", _build_blob, True, 90.0, 0, "star-shaped noise-displaced spheres"),
        _spec("metaballs", _build_metaballs, True, 90.0, None, "blended anisotropic Gaussians"),
        _spec("torus", _build_torus, True, 90.0, 1, "tori with varying sections, torus knots"),
        _spec("genus", _build_genus, True, 90.0, None, "smooth genus 2-5 solids"),
        _spec("superquadric", _build_superquadric, True, 90.0, 0, "tapered/bent superellipsoids"),
        _spec("relief", _build_relief, True, 30.0, 0, "closed slabs with a height-field top"),
        _spec("terrain", _build_terrain, False, 90.0, 0, "open height-field patches (boundary)"),
        _spec("twisted_bar", _build_twisted_bar, True, 30.0, 0, "twisted and bent polygonal bars"),
        _spec("tube", _build_tube, True, 30.0, 0, "tubes swept along space curves"),
    ]
)

CATEGORIES: tuple[str, ...] = tuple(_SPECS)


def category_info(category: str) -> CategoryInfo:
    """What `category` promises (closed or open, feature angle, genus)."""
    _check_category(category)
    return _SPECS[category].info


def _check_category(category: str) -> None:
    if category not in _SPECS:
        raise ValueError(f"unknown shape category {category!r}; known: {', '.join(CATEGORIES)}")


def category_key(category: str) -> int:
    """A stable integer for a category name (CRC-32), used to seed its random streams."""
    return zlib.crc32(category.encode("utf-8"))


# --------------------------------------------------------------------------------------
# Public entry point
# --------------------------------------------------------------------------------------

MAX_ATTEMPTS = 12


def _target_vertices(rng: np.random.Generator, min_vertices: int, max_vertices: int) -> int:
    """A target count drawn log-uniformly from the inner part of the range."""
    lo, hi = min_vertices * 1.1, max_vertices / 1.1
    if lo >= hi:
        return int(round(np.sqrt(min_vertices * max_vertices)))
    return int(round(np.exp(rng.uniform(np.log(lo), np.log(hi)))))


def generate_shape(
    category: str,
    seed: int,
    instance: int,
    *,
    min_vertices: int = 1000,
    max_vertices: int = 6000,
) -> tuple[np.ndarray, np.ndarray]:
    """One procedural shape, remeshed, cleaned and in the canonical frame.

    Args:
      category: an entry of `CATEGORIES`.
      seed: dataset seed (non-negative integer).
      instance: instance number within the category (non-negative integer).
      min_vertices, max_vertices: the vertex count lands in this range.

    Returns:
      `(vertices float64 [n, 3], faces int32 [f, 3])`, centred on the bounding box with
      longest side 1; closed and outward-oriented unless `category_info(category).closed`
      is `False`.

    Raises:
      ValueError: unknown category, negative seed or instance, bad vertex range.
      RuntimeError: no valid mesh after `MAX_ATTEMPTS` draws (the message says why).
    """
    _check_category(category)
    if int(seed) != seed or seed < 0 or int(instance) != instance or instance < 0:
        raise ValueError(f"seed and instance must be non-negative integers, got {seed}, {instance}")
    if not 4 <= min_vertices <= max_vertices:
        raise ValueError(
            f"need 4 <= min_vertices <= max_vertices, got {min_vertices}, {max_vertices}"
        )
    spec = _SPECS[category]
    key = category_key(category)
    last = ""
    for attempt in range(MAX_ATTEMPTS):
        shape_rng = np.random.default_rng([int(seed), key, int(instance), attempt, 0])
        mesh_rng = np.random.default_rng([int(seed), key, int(instance), attempt, 1])
        try:
            built = spec.build(shape_rng)
            v, f = built[:2]
            genus = built[2] if len(built) > 2 else spec.info.genus
            target = _target_vertices(mesh_rng, min_vertices, max_vertices)
            v, f = remesh(
                v,
                f,
                min_vertices=min_vertices,
                max_vertices=max_vertices,
                target_vertices=target,
                feature_angle=spec.info.feature_angle,
            )
        except (_Reject, ValueError) as exc:
            last = str(exc)
            continue
        problems = mesh_problems(v, f, closed=spec.info.closed, genus=genus)
        if problems:
            last = "; ".join(problems)
            continue
        frame = canonical_frame(v)
        return frame.apply(v), f.astype(np.int32)
    raise RuntimeError(
        f"no valid {category!r} mesh for seed {seed}, instance {instance} after "
        f"{MAX_ATTEMPTS} attempts; last problem: {last}"
    )


__all__ = [
    "CATEGORIES",
    "GENERATOR_VERSION",
    "MAX_ATTEMPTS",
    "CategoryInfo",
    "category_info",
    "category_key",
    "clean_mesh",
    "decimate",
    "generate_shape",
    "mesh_area",
    "mesh_problems",
    "remesh",
]

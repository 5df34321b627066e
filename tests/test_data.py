"""Procedural shapes, remeshing, dataset files, splits, folder loading and the CLI."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import scipy.sparse
import scipy.sparse.csgraph
import trimesh

from dmd_jax.cli import main
from dmd_jax.data import (
    CATEGORIES,
    DEFAULT_TEST_INTER,
    SPLITS,
    category_info,
    clean_mesh,
    convert_folder,
    generate_shape,
    intra_test_indices,
    load_dataset,
    load_mesh_folder,
    make_dataset,
    remesh,
)
from dmd_jax.io import load_mesh, save_mesh
from dmd_jax.mesh import validate_mesh
from tests.conftest import icosphere, shared_mesh_path, tetrahedron

SMALL = dict(min_vertices=300, max_vertices=1500)


# --------------------------------------------------------------------------------------
# Independent mesh checks (NumPy / scipy / trimesh, not the generator's own checker)
# --------------------------------------------------------------------------------------


def _fans_per_vertex(faces: np.ndarray, n_vertex: int) -> np.ndarray:
    """Number of edge-connected face fans around every vertex (1 on a manifold vertex).

    Corners (face, vertex) of the same vertex are joined when their faces share an edge
    through that vertex; a vertex whose corners form several groups is non-manifold.
    """
    f = np.asarray(faces, np.int64)
    n_face = f.shape[0]
    corner = np.arange(3 * n_face)
    apex = f.ravel()
    nxt = f[:, [1, 2, 0]].ravel()
    prv = f[:, [2, 0, 1]].ravel()
    keys = np.concatenate([apex * n_vertex + nxt, apex * n_vertex + prv])
    owners = np.concatenate([corner, corner])
    order = np.argsort(keys, kind="stable")
    keys, owners = keys[order], owners[order]
    same = keys[1:] == keys[:-1]
    a, b = owners[:-1][same], owners[1:][same]
    adj = scipy.sparse.coo_matrix((np.ones(a.size), (a, b)), shape=(3 * n_face, 3 * n_face))
    _, label = scipy.sparse.csgraph.connected_components(adj, directed=False)
    pairs = np.unique(np.stack([apex, label], 1), axis=0)
    return np.bincount(pairs[:, 0], minlength=n_vertex)


def _min_angles_deg(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    t = v[f]
    angles = []
    for k in range(3):
        a = t[:, (k + 1) % 3] - t[:, k]
        b = t[:, (k + 2) % 3] - t[:, k]
        cos = (a * b).sum(1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
        angles.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return np.min(angles, axis=0)


def _check_training_mesh(v, f, *, closed, genus, lo, hi):
    v2, f2 = validate_mesh(v, f)
    np.testing.assert_array_equal(v2, v)
    np.testing.assert_array_equal(f2, f)
    assert v.dtype == np.float64 and f.dtype == np.int32
    assert lo <= v.shape[0] <= hi
    # Canonical frame: bounding box centred, longest side 1.
    bb_lo, bb_hi = v.min(0), v.max(0)
    np.testing.assert_allclose((bb_lo + bb_hi) / 2, 0.0, atol=1e-12)
    assert abs((bb_hi - bb_lo).max() - 1.0) < 1e-12
    # Clean: no duplicate or unreferenced vertices, no duplicate or degenerate faces.
    assert np.unique(v, axis=0).shape[0] == v.shape[0]
    assert np.bincount(f.ravel(), minlength=v.shape[0]).min() > 0
    assert np.unique(np.sort(f, axis=1), axis=0).shape[0] == f.shape[0]
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.area_faces.min() > 1e-6 * mesh.area_faces.mean()
    assert _min_angles_deg(v, f).min() > 1.0
    assert mesh.is_winding_consistent
    assert np.all(_fans_per_vertex(f, v.shape[0]) == 1)
    n_components = scipy.sparse.csgraph.connected_components(
        scipy.sparse.coo_matrix(
            (np.ones(3 * f.shape[0]), (f.ravel(), f[:, [1, 2, 0]].ravel())),
            shape=(v.shape[0],) * 2,
        ),
        directed=False,
    )[0]
    assert n_components == 1
    edges = np.sort(mesh.edges, axis=1)
    _, uses = np.unique(edges, axis=0, return_counts=True)
    assert uses.max() <= 2
    if closed:
        assert mesh.is_watertight
        assert mesh.volume > 0  # outward orientation
        if genus is not None:
            euler = v.shape[0] - uses.size + f.shape[0]
            assert euler == 2 - 2 * genus
    else:
        assert (uses == 1).any()


# --------------------------------------------------------------------------------------
# Shapes
# --------------------------------------------------------------------------------------


def test_categories():
    assert len(CATEGORIES) >= 12
    assert len(set(CATEGORIES)) == len(CATEGORIES)
    assert all(c in CATEGORIES for c in DEFAULT_TEST_INTER)
    assert 2 <= len(DEFAULT_TEST_INTER) <= 3
    open_ones = [c for c in CATEGORIES if not category_info(c).closed]
    assert open_ones == ["terrain"]
    with pytest.raises(ValueError, match="unknown shape category"):
        category_info("chair")


@pytest.mark.parametrize("category", CATEGORIES)
def test_every_category_gives_a_valid_mesh(category):
    info = category_info(category)
    for instance in (0, 1):
        v, f = generate_shape(category, 3, instance, **SMALL)
        _check_training_mesh(v, f, closed=info.closed, genus=info.genus, lo=300, hi=1500)


@pytest.mark.parametrize("category", ["gear", "vase"])
def test_default_vertex_range(category):
    v, f = generate_shape(category, 0, 0)
    info = category_info(category)
    _check_training_mesh(v, f, closed=info.closed, genus=info.genus, lo=1000, hi=6000)


def test_genus_category_has_its_holes():
    # The genus category promises no fixed genus, but each shape is 2 to 5.
    genera = set()
    for instance in range(3):
        v, f = generate_shape("genus", 0, instance, **SMALL)
        mesh = trimesh.Trimesh(v, f, process=False)
        genera.add(int(round((2 - mesh.euler_number) / 2)))
    assert genera <= {2, 3, 4, 5} and genera


def test_determinism():
    a = generate_shape("gear", 7, 2, **SMALL)
    b = generate_shape("gear", 7, 2, **SMALL)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    c = generate_shape("gear", 7, 3, **SMALL)
    d = generate_shape("gear", 8, 2, **SMALL)
    for other in (c, d):
        assert other[0].shape != a[0].shape or not np.array_equal(other[0], a[0])


def test_generate_shape_rejects_bad_arguments():
    with pytest.raises(ValueError, match="unknown shape category"):
        generate_shape("chair", 0, 0)
    with pytest.raises(ValueError, match="non-negative"):
        generate_shape("blob", -1, 0)
    with pytest.raises(ValueError, match="min_vertices"):
        generate_shape("blob", 0, 0, min_vertices=2000, max_vertices=1000)


def test_remesh_lands_in_range_and_keeps_sharp_edges():
    import manifold3d

    # A unit cube minus a through hole: its 12 outer edges are analytic references.
    solid = manifold3d.Manifold.cube((1.0, 1.0, 1.0), True) - manifold3d.Manifold.cylinder(
        2.0, 0.2, -1.0, 96, True
    )
    mesh = solid.to_mesh64()
    v0 = np.asarray(mesh.vert_properties)[:, :3]
    f0 = np.asarray(mesh.tri_verts).astype(np.int64)
    t = np.linspace(-0.5, 0.5, 41)
    edge_points = []
    for axis in range(3):
        for s1 in (-0.5, 0.5):
            for s2 in (-0.5, 0.5):
                p = np.zeros((t.size, 3))
                p[:, axis] = t
                p[:, (axis + 1) % 3] = s1
                p[:, (axis + 2) % 3] = s2
                edge_points.append(p)
    edge_points = np.concatenate(edge_points)

    def edge_deviation(feature_angle):
        v, f = remesh(v0, f0, min_vertices=800, max_vertices=2000, feature_angle=feature_angle)
        assert 800 <= v.shape[0] <= 2000
        out = trimesh.Trimesh(v, f, process=False)
        _, dist, _ = trimesh.proximity.closest_point(out, edge_points)
        mean_edge = out.edges_unique_length.mean()
        return dist.max() / mean_edge

    kept = edge_deviation(30.0)
    rounded = edge_deviation(180.0)
    assert kept < 0.01  # corners of the cube stay on the cube's edges
    assert rounded > 10 * kept  # without feature preservation they are cut off


def test_remesh_and_clean_errors_and_cleaning():
    v, f = icosphere(3)
    with pytest.raises(ValueError, match="min_vertices"):
        remesh(v, f, min_vertices=10, max_vertices=5)
    with pytest.raises(ValueError, match="missed the vertex range"):
        remesh(v, f, min_vertices=1000, max_vertices=1001, max_rounds=1, target_vertices=4000)
    # Splitting every face into its own vertices, plus a duplicate face, then cleaning,
    # gives back the original connectivity.
    split_v = v[f].reshape(-1, 3)
    split_f = np.arange(split_v.shape[0]).reshape(-1, 3)
    split_f = np.concatenate([split_f, split_f[:1]])
    cv, cf = clean_mesh(split_v, split_f)
    assert cv.shape == v.shape and cf.shape == f.shape
    assert trimesh.Trimesh(cv, cf, process=False).is_watertight
    # One face wound the wrong way is turned back; a sphere wound inward is turned outward.
    bad = f.copy()
    bad[5] = bad[5, ::-1]
    for faces in (bad, f[:, ::-1]):
        assert not trimesh.Trimesh(v, faces, process=False).is_winding_consistent or (
            trimesh.Trimesh(v, faces, process=False).volume < 0
        )
        cv, cf = clean_mesh(v, faces)
        fixed = trimesh.Trimesh(cv, cf, process=False)
        assert fixed.is_winding_consistent and fixed.volume > 0
    kept_v, kept_f = clean_mesh(v, bad, orient=False)
    np.testing.assert_array_equal(kept_f, bad)


# --------------------------------------------------------------------------------------
# Splits and datasets
# --------------------------------------------------------------------------------------


def test_intra_test_indices():
    a = intra_test_indices(40, category="gear", seed=0, intra_fraction=0.2)
    assert a == intra_test_indices(40, category="gear", seed=0, intra_fraction=0.2)
    assert len(a) == 8 and a <= set(range(40))
    assert a != intra_test_indices(40, category="gear", seed=1, intra_fraction=0.2)
    assert a != intra_test_indices(40, category="vase", seed=0, intra_fraction=0.2)
    assert len(intra_test_indices(2, category="x", seed=0, intra_fraction=0.2)) == 1
    assert intra_test_indices(5, category="x", seed=0, intra_fraction=0.0) == set()
    with pytest.raises(ValueError, match="intra_fraction"):
        intra_test_indices(5, category="x", seed=0, intra_fraction=1.0)


TINY_CATEGORIES = ("blob", "gear", "torus")
TINY = dict(
    per_category=5,
    seed=4,
    categories=TINY_CATEGORIES,
    test_inter=("torus",),
    min_vertices=300,
    max_vertices=800,
    progress=False,
)


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny") / "ds"
    return make_dataset(out, workers=1, **TINY)


def test_split_protocol(tiny_dataset):
    ds = tiny_dataset
    assert ds.counts() == {"train": 8, "test_intra": 2, "test_inter": 5}
    assert {r.category for r in ds.split("test_inter")} == {"torus"}
    for cat in ("blob", "gear"):
        train = {r.instance for r in ds.split("train") if r.category == cat}
        test = {r.instance for r in ds.split("test_intra") if r.category == cat}
        assert not train & test and train | test == set(range(5))
        assert test == intra_test_indices(5, category=cat, seed=4, intra_fraction=0.2)
    assert all(r.category != "torus" for s in ("train", "test_intra") for r in ds.split(s))
    with pytest.raises(ValueError, match="unknown split"):
        ds.split("validation")


def test_manifest_round_trip(tiny_dataset):
    ds = tiny_dataset
    again = load_dataset(ds.root)
    manifest = json.loads((ds.root / "manifest.json").read_text())
    assert manifest["version"] == 1 and manifest["seed"] == 4
    assert manifest["generator"]["min_vertices"] == 300
    assert manifest["test_inter"] == ["torus"]
    assert [m["id"] for m in manifest["meshes"]] == [r.id for r in again.records]
    assert again.verify() == []
    rec = again.split("train")[0]
    v, f = rec.load()
    assert (v.shape[0], f.shape[0]) == (rec.n_vertex, rec.n_face)
    ref_v, ref_f = generate_shape(rec.category, 4, rec.instance, min_vertices=300, max_vertices=800)
    np.testing.assert_array_equal(v, ref_v.astype(np.float32).astype(np.float64))
    np.testing.assert_array_equal(f, ref_f)
    with np.load(rec.source, allow_pickle=False) as data:
        assert data["vertices"].dtype == np.float32 and data["faces"].dtype == np.int32
    pairs = again.arrays("test_intra")
    assert len(pairs) == 2 and all(p[0].shape[1] == 3 for p in pairs)


def test_parallel_run_matches_serial(tiny_dataset, tmp_path):
    ds = make_dataset(tmp_path / "par", workers=2, **TINY)
    serial = [(m["id"], m["split"], m["sha256"]) for m in tiny_dataset.manifest["meshes"]]
    parallel = [(m["id"], m["split"], m["sha256"]) for m in ds.manifest["meshes"]]
    assert serial == parallel


def test_load_dataset_errors(tiny_dataset, tmp_path):
    with pytest.raises(FileNotFoundError, match="no such dataset"):
        load_dataset(tmp_path / "absent")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="unfinished run"):
        load_dataset(tmp_path / "empty")
    copy = tmp_path / "copy"
    shutil.copytree(tiny_dataset.root, copy)
    manifest_path = copy / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    for change, message in (
        ({"version": 99}, "version 99"),
        ({"version": "1"}, "must be an integer"),
        ({"format": "other"}, "not a dmd_jax-mesh-dataset"),
        ({"meshes": {}}, "must be a list"),
        ({"meshes": [dict(manifest["meshes"][0], split="val")]}, "unknown split"),
        ({"meshes": [manifest["meshes"][0]] * 2}, "appears twice"),
    ):
        manifest_path.write_text(json.dumps(dict(manifest, **change)))
        with pytest.raises(ValueError, match=message):
            load_dataset(copy)
    manifest_path.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_dataset(copy)
    manifest_path.write_text(json.dumps(manifest))
    first = copy / manifest["meshes"][0]["file"]
    np.savez(first, vertices=np.zeros((3, 3), np.float32), faces=np.array([[0, 1, 2]], np.int32))
    assert load_dataset(copy).verify() == [manifest["meshes"][0]["id"]]
    first.unlink()
    with pytest.raises(FileNotFoundError, match="missing"):
        load_dataset(copy)


def test_make_dataset_argument_errors(tmp_path):
    with pytest.raises(ValueError, match="not among the categories"):
        make_dataset(tmp_path / "a", per_category=1, test_inter=("chair",), progress=False)
    with pytest.raises(ValueError, match="nothing would be left"):
        make_dataset(tmp_path / "a", per_category=1, categories=("blob",), test_inter=("blob",))
    with pytest.raises(ValueError, match="per_category"):
        make_dataset(tmp_path / "a", per_category=0)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "note.txt").write_text("keep me")
    with pytest.raises(FileExistsError, match="not empty"):
        make_dataset(tmp_path / "full", per_category=1, progress=False)


# --------------------------------------------------------------------------------------
# Mesh folders
# --------------------------------------------------------------------------------------


def _write_folder(root):
    """Two flat categories in three formats, with a split-vertex OBJ to clean."""
    v, f = icosphere(2)
    t_v, t_f = tetrahedron()
    (root / "spheres").mkdir(parents=True, exist_ok=True)
    for i in range(4):
        save_mesh(root / "spheres" / f"s{i}.obj", v * (i + 1) + i, f)
    (root / "tets").mkdir()
    save_mesh(root / "tets" / "a.off", t_v, t_f)
    save_mesh(root / "tets" / "b.ply", t_v * 2, t_f)
    # Every face with its own three vertices, as OBJ exporters write UV seams.
    split_v = t_v[t_f].reshape(-1, 3)
    save_mesh(root / "tets" / "c.obj", split_v, np.arange(12).reshape(4, 3))
    (root / "tets" / "readme.txt").write_text("not a mesh")


def test_load_mesh_folder_flat(tmp_path):
    _write_folder(tmp_path)
    ds = load_mesh_folder(tmp_path, test_inter=("tets",), seed=0)
    assert ds.categories == ("spheres", "tets")
    assert {r.id for r in ds.split("test_inter")} == {"tets/a", "tets/b", "tets/c"}
    intra = {r.instance for r in ds.split("test_intra")}
    assert len(intra) == 1 and intra < {"s0", "s1", "s2", "s3"}
    cleaned_v, cleaned_f = next(r for r in ds.records if r.id == "tets/c").load()
    assert cleaned_v.shape == (4, 3) and cleaned_f.shape == (4, 3)
    sv, sf = next(r for r in ds.records if r.id == "spheres/s2").load()
    ref_v, ref_f = load_mesh(tmp_path / "spheres" / "s2.obj")
    np.testing.assert_array_equal(sf, ref_f)
    np.testing.assert_allclose(sv, (ref_v - (ref_v.max(0) + ref_v.min(0)) / 2) / 6.0, atol=1e-12)
    no_inter = load_mesh_folder(tmp_path)
    assert no_inter.counts()["test_inter"] == 0
    with pytest.raises(ValueError, match="not among the categories"):
        load_mesh_folder(tmp_path, test_inter=("chairs",))
    (tmp_path / "empty_root").mkdir()
    with pytest.raises(ValueError, match="no mesh files"):
        load_mesh_folder(tmp_path / "empty_root")
    with pytest.raises(FileNotFoundError):
        load_mesh_folder(tmp_path / "absent")


def test_load_mesh_folder_shapenet_layout(tmp_path):
    v, f = icosphere(1)
    ids = ["1a2b3c", "4d5e6f", "7a8b9c"]
    for i, inst in enumerate(ids):
        models = tmp_path / "02691156" / inst / "models"
        models.mkdir(parents=True)
        save_mesh(models / "model_normalized.obj", v + i, f)
        # ShapeNetCore v2 folders also hold other files, ignored here.
        (models / "model_normalized.json").write_text("{}")
    flat = tmp_path / "03001627"
    flat.mkdir()
    save_mesh(flat / "chair1.obj", v, f)
    save_mesh(flat / "chair2.obj", v * 2, f)
    ds = load_mesh_folder(tmp_path, test_inter=("03001627",))
    assert sorted(r.instance for r in ds.records if r.category == "02691156") == ids
    assert {r.split for r in ds.records if r.category == "02691156"} == {"train", "test_intra"}
    for r in ds.records:
        rv, rf = r.load()
        assert rv.shape == v.shape and rf.shape == f.shape


def test_folder_remesh_into_range(tmp_path):
    path = shared_mesh_path("bunny.off")
    (tmp_path / "animals").mkdir()
    shutil.copy(path, tmp_path / "animals" / "bunny.off")
    ds = load_mesh_folder(tmp_path, remesh=True, min_vertices=500, max_vertices=1200)
    v, f = ds.records[0].load()
    assert 500 <= v.shape[0] <= 1200
    assert abs(np.ptp(v, axis=0).max() - 1.0) < 1e-12
    v2, f2 = ds.records[0].load()
    np.testing.assert_array_equal(v, v2)


def test_convert_folder_and_skips_bad_files(tmp_path):
    src = tmp_path / "src"
    _write_folder(src)
    (src / "tets" / "broken.obj").write_text("")
    with pytest.warns(UserWarning, match="skipped"):
        ds = convert_folder(src, tmp_path / "out", test_inter=("tets",), workers=1, progress=False)
    assert [s["id"] for s in ds.manifest["skipped"]] == ["tets/broken"]
    assert len(ds) == 7 and ds.manifest["source"] == "folder"
    lazy = load_mesh_folder(src, test_inter=("tets",))
    for rec in ds.records:
        ref = next(r for r in lazy.records if r.id == rec.id)
        assert rec.split == ref.split
        np.testing.assert_allclose(rec.load()[0], ref.load()[0], atol=1e-6)
    with pytest.raises(ValueError, match="outside the input folder"):
        convert_folder(src, src / "inside", progress=False)


# --------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------


def test_cli_make_dataset(tmp_path, capsys):
    out = tmp_path / "ds"
    args = [
        "make-dataset",
        "--out",
        str(out),
        "--per-category",
        "2",
        "--seed",
        "1",
        "--workers",
        "1",
        "--categories",
        "blob,extrusion,superquadric",
        "--test-inter",
        "superquadric",
        "--min-vertices",
        "300",
        "--max-vertices",
        "700",
        "--no-progress",
    ]
    assert main(args) == 0
    assert "wrote 6 meshes" in capsys.readouterr().out
    ds = load_dataset(out)
    assert ds.counts() == {"train": 2, "test_intra": 2, "test_inter": 2}
    assert set(ds.manifest["meshes"][0]) >= {"id", "category", "instance", "split", "file"}
    assert all(s in SPLITS for s in ds.counts())
    assert main(args) == 2
    assert "not empty" in capsys.readouterr().err
    assert main(args + ["--overwrite"]) == 0
    assert main(["make-dataset", "--out", str(tmp_path / "x")]) == 2
    assert "--per-category is required" in capsys.readouterr().err


def test_cli_make_dataset_from_folder(tmp_path, capsys):
    src = tmp_path / "src"
    _write_folder(src)
    out = tmp_path / "out"
    rc = main(
        ["make-dataset", "--out", str(out), "--from-folder", str(src), "--workers", "1"]
        + ["--no-progress"]
    )
    assert rc == 0
    assert "wrote 7 meshes" in capsys.readouterr().out
    assert load_dataset(out).manifest["source"] == "folder"

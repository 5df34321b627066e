"""The smoothing controller: its statistics are scale-free and read what they claim, its
training set's search agrees with `denoise`, and a fit learns a choice that depends on
the statistics."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import icosphere, rules_only

from dmd_jax import add_noise, controller, denoise, load_pretrained
from dmd_jax.controller_features import FEATURE_NAMES, N_FEATURES, features
from dmd_jax.data import smoothing_set
from dmd_jax.metrics import face_normal_errors_deg


@pytest.fixture(scope="module")
def sphere():
    v, f = icosphere(3)
    return np.asarray(v, np.float64), np.asarray(f, np.int32)


def _rotation(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).standard_normal((3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_features_are_invariant_to_pose_and_scale(sphere):
    v, f = sphere
    noisy = add_noise(0, v, f, "gaussian", 0.3, units="edge", direction="normal")
    a = features(noisy, f)
    b = features(noisy @ _rotation(1).T * 1e3 + 7.0, f)
    assert a.shape == (N_FEATURES,) == (len(FEATURE_NAMES),)
    np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-9)


def test_features_read_noise_strength_and_direction(sphere):
    v, f = sphere
    named = lambda x: dict(zip(FEATURE_NAMES, features(x, f), strict=True))  # noqa: E731
    light = named(add_noise(0, v, f, "gaussian", 0.05, units="edge", direction="normal"))
    heavy = named(add_noise(0, v, f, "gaussian", 0.5, units="edge", direction="normal"))
    assert heavy["rough_q50"] > 3 * light["rough_q50"]
    assert heavy["plane_rms"] > 3 * light["plane_rms"]
    iso = named(add_noise(0, v, f, "gaussian", 0.5, units="edge"))
    scan = named(add_noise(0, v, f, "scanner", 0.5, units="edge", view=[0.0, 0.0, 1.0]))
    # One view direction: the noise directions' second moment is one-dimensional.
    assert scan["disp_anisotropy"] > 0.8 and iso["disp_anisotropy"] < 0.5
    # Along the normals: little tangential displacement; isotropic noise moves vertices
    # within the surface as much as across it.
    assert iso["tangent_rms"] > 2 * heavy["tangent_rms"]
    # Correlated noise survives Laplacian steps that white noise does not.
    assert scan["rough_ratio_16"] > heavy["rough_ratio_16"]
    assert light["boundary_share"] == 0.0


def test_an_irregular_triangulation_is_not_read_as_noise():
    """A clean sphere re-triangulated irregularly (vertices moved within the surface) has
    a large tangential umbrella vector, as isotropic noise has, but its vertices stay on
    their neighbours' planes: its noise statistic is the clean mesh's, far below light
    noise's, and the triangulation statistics say what changed. (A finer sphere than the
    other tests': on a coarse one the curvature alone puts vertices off their neighbours'
    planes by as much as noise of 0.05 edges.)"""
    v, f = icosphere(4)
    v, f = np.asarray(v, np.float64), np.asarray(f, np.int32)

    def light_noise(x, ff):  # 0.1 mean edges along the normals (numpy: no compilation)
        e = np.sort(ff[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        edge = np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1).mean()
        n = x / np.linalg.norm(x, axis=1, keepdims=True)  # a sphere's normals
        return x + 0.1 * edge * np.random.default_rng(0).standard_normal((len(x), 1)) * n

    named = lambda x, ff: dict(zip(FEATURE_NAMES, features(x, ff), strict=True))  # noqa: E731
    jitter = {"triangulation": {"kind": "jitter", "seed": 1, "sigma": 0.3}}
    vj, fj = smoothing_set.retriangulate(v, f, jitter)
    clean, irregular = named(v, f), named(vj, fj)
    light = named(light_noise(v, f), f)
    assert irregular["tangent_rms"] > 5 * clean["tangent_rms"]
    assert irregular["plane_rms"] < 1.3 * clean["plane_rms"] < light["plane_rms"] / 2
    assert irregular["edge_spread"] > 3 * clean["edge_spread"]
    assert irregular["angle_q10"] < clean["angle_q10"] / 2
    # Area-weighted and in local edges: the same with the triangle sizes varied.
    noisy_irregular = named(light_noise(vj, fj), fj)
    assert noisy_irregular["plane_rms"] == pytest.approx(light["plane_rms"], rel=0.25)


def test_retriangulations_keep_a_clean_mesh_of_the_crop(sphere):
    v, f = sphere
    for t in (
        {"kind": "given"},
        {"kind": "jitter", "seed": 0, "sigma": 0.2},
        {"kind": "decimated", "keep": 0.4},
        {"kind": "coarse", "faces": 120},
        {"kind": "anisotropic", "stretch": 3.0, "axis": [1.0, 2.0, 0.5]},
    ):
        rv, rf = smoothing_set.retriangulate(v, f, {"patch_faces": 500, "triangulation": t})
        assert rv.dtype == np.float64 and rf.dtype == np.int32 and rf.max() < len(rv)
        want = {"given": len(f), "decimated": 500, "coarse": 120}.get(t["kind"], len(f))
        assert abs(len(rf) - want) <= 0.05 * want + 2, t
        # Every re-triangulation keeps the vertices on a smooth closed surface (their
        # distance from the centre: the sphere's, or the stretched ellipsoid's range).
        r = np.linalg.norm(rv - rv.mean(axis=0), axis=1)
        if t["kind"] in ("given", "jitter"):
            assert np.ptp(r) < 0.02
        elif t["kind"] != "anisotropic":
            assert np.ptp(r) < 0.15  # decimated: vertices placed on the chords
    again = smoothing_set.retriangulate(
        v, f, {"triangulation": {"kind": "jitter", "seed": 0, "sigma": 0.2}}
    )
    rv, _ = smoothing_set.retriangulate(
        v, f, {"triangulation": {"kind": "jitter", "seed": 0, "sigma": 0.2}}
    )
    np.testing.assert_array_equal(again[0], rv)  # a pure function of the spec


@pytest.mark.slow  # 20-40 s on 2 cores (two vertex updates compiled); `make test-slow`
def test_the_search_is_what_denoise_does(sphere):
    """Entry [p, u, k] of the search is `denoise(presmooth=p, iterations=k)` with that
    vertex update (a noisy sphere: no vertex is held)."""
    v, f = sphere
    noisy = add_noise(3, v, f, "gaussian", 0.3, units="edge", direction="normal")
    bundle = load_pretrained()
    errors, first = smoothing_set.pass_errors(noisy, v, f, bundle)
    grid = smoothing_set.PRESMOOTH_GRID
    assert errors.shape == (len(grid), 2, smoothing_set.SEARCH_PASSES + 1)
    for p, u, k in ((0, 0, 1), (1, 1, 3)):
        b = bundle.with_vertex_update(smoothing_set.UPDATES[u])
        out = denoise(noisy, f, b, presmooth=grid[p], iterations=k)
        want = float(np.mean(face_normal_errors_deg(out, v, f)))
        assert errors[p, u, k] == pytest.approx(want, rel=1e-4)
    assert errors[0, 0, 0] == pytest.approx(
        float(np.mean(face_normal_errors_deg(noisy, v, f))), rel=1e-9
    )
    assert first.shape == (2,) and first[0] > 0 and first[1] > 0


@pytest.fixture(scope="module")
def impulse_part():
    """A subdivided chamfered box (flat faces, creases) under impulse noise: most
    vertices stay exactly in their planes, and `denoise` holds them."""
    from dmd_jax.data.stress import stress_shape, subdivide

    v, f = subdivide(*stress_shape("chamfered_box"), levels=1)
    v, f = np.asarray(v, np.float64), np.asarray(f, np.int32)
    noisy = add_noise(5, v, f, "impulse", 0.5, units="edge")
    return v, f, noisy


def test_held_vertices_are_those_denoise_holds(impulse_part, sphere):
    v, f, noisy = impulse_part
    held = smoothing_set.held_vertices(noisy, f)
    assert 0 < held.sum() < len(held)
    _, info = denoise(noisy, f, load_pretrained(), iterations=1, return_info=True)
    assert int(held.sum()) == info.exact_vertices + info.still_vertices
    vs, fs = sphere
    noisy_sphere = add_noise(3, vs, fs, "gaussian", 0.3, units="edge", direction="normal")
    assert not smoothing_set.held_vertices(noisy_sphere, fs).any()


@pytest.mark.slow  # 20-40 s on 2 cores; `make test-slow`
def test_the_search_holds_what_denoise_holds(impulse_part):
    """Where `denoise` holds vertices, entry [p, u, k] of the search is still
    `denoise(presmooth=p, iterations=k)`: the search holds them too (search version 2;
    version 1 moved them, 4-7° off on impulse-noised CAD crops)."""
    v, f, noisy = impulse_part
    bundle = load_pretrained()
    errors, _ = smoothing_set.pass_errors(noisy, v, f, bundle)
    grid = smoothing_set.PRESMOOTH_GRID
    for p, u, k in ((0, 0, 2), (1, 1, 1), (3, 0, 1)):
        b = bundle.with_vertex_update(smoothing_set.UPDATES[u])
        out = denoise(noisy, f, b, presmooth=grid[p], iterations=k)
        want = float(np.mean(face_normal_errors_deg(out, v, f)))
        assert errors[p, u, k] == pytest.approx(want, rel=1e-4)


def test_an_older_search_is_refused_and_redone_where_vertices_are_held(tmp_path, monkeypatch):
    """`load` refuses examples of an older search version; `research` redoes the search
    of those whose mesh has held vertices and keeps the others' errors."""
    from dmd_jax.data.stress import stress_shape, subdivide

    part = subdivide(*stress_shape("chamfered_box"), levels=1)
    part = np.asarray(part[0], np.float64), np.asarray(part[1], np.int32)
    ball = icosphere(2)
    ball = np.asarray(ball[0], np.float64), np.asarray(ball[1], np.int32)

    class TwoMeshes:
        def counts(self):
            return {"stress": 2}

        def mesh(self, spec):
            return part if spec["mesh"] == 0 else ball

    sources = TwoMeshes()
    (tmp_path / "examples").mkdir()
    (tmp_path / "manifest.json").write_text(json.dumps({"sources": sources.counts()}))
    old = np.zeros((2, 2, 3))
    for i, (kind, level) in enumerate((("impulse", 0.5), ("gaussian_normal", 0.3))):
        spec = {"index": i, "source": "stress", "mesh": i, "kind": kind, "level": level}
        spec["noise_seed"] = 7
        clean, mesh_faces = sources.mesh(spec)
        _, noisy, mesh_faces = smoothing_set.noisy_example(spec, clean, mesh_faces)
        np.savez(
            tmp_path / "examples" / f"{i:05d}.npz",
            features=features(noisy, mesh_faces),
            features_version=controller_features_version(),
            errors=old,
            first_pass=np.zeros(2),
            default_error=1.0,
            spec=json.dumps(spec),
            n_faces=len(mesh_faces),
            noisy_digest=smoothing_set.mesh_digest(noisy, mesh_faces),
        )  # no search_version: the first search
    with pytest.raises(ValueError, match="--research"):
        smoothing_set.load(tmp_path)
    searched = []

    def fake_search(noisy, clean, faces, bundle, held):
        searched.append(int(held.sum()))
        return np.ones((2, 2, 3)), np.ones(2)

    monkeypatch.setattr(smoothing_set, "pass_errors", fake_search)
    report = smoothing_set.research(tmp_path, sources=sources, bundle=object(), say=print)
    assert report == {"checked": 2, "researched": 1, "rejected": []}
    assert len(searched) == 1 and searched[0] > 0
    data = smoothing_set.load(tmp_path)
    np.testing.assert_array_equal(data["errors"][0], np.ones((2, 2, 3)))  # held: redone
    np.testing.assert_array_equal(data["errors"][1], old)  # none held: the same search
    assert smoothing_set.research(tmp_path, sources=sources, bundle=object())["checked"] == 0


class OneBall:
    """Sources of a controller set holding one mesh, an icosphere (`smoothing_set.Sources`)."""

    def __init__(self):
        v, f = icosphere(2)
        self.ball = np.asarray(v, np.float64), np.asarray(f, np.int32)

    def counts(self):
        return {"stress": 1}

    def mesh(self, spec):
        return self.ball


def test_a_set_searched_again_for_another_network(tmp_path, monkeypatch):
    """`search_with` copies a set with the search and the default call's error redone
    for another network, records its digest, resumes, and `load` refuses a set mixing
    networks."""
    import shutil

    import dmd_jax
    from dmd_jax import checkpoints
    from dmd_jax.metrics import face_normal_errors_deg

    sources, src, out = OneBall(), tmp_path / "src", tmp_path / "out"
    (src / "examples").mkdir(parents=True)
    (src / "manifest.json").write_text(json.dumps({"sources": sources.counts()}))
    noisy_meshes = []
    for i, level in enumerate((0.2, 0.5)):
        spec = {"index": i, "source": "stress", "mesh": 0, "kind": "gaussian_normal"}
        spec.update(level=level, noise_seed=3 + i)
        clean, faces = sources.mesh(spec)
        clean, noisy, faces = smoothing_set.noisy_example(spec, clean, faces)
        noisy_meshes.append((noisy, clean, faces))
        np.savez(
            src / "examples" / f"{i:05d}.npz",
            features=features(noisy, faces),
            features_version=controller_features_version(),
            errors=np.zeros((2, 2, 3)),
            search_version=smoothing_set.SEARCH_VERSION,
            first_pass=np.zeros(2),
            default_error=1.0,
            spec=json.dumps(spec),
            n_faces=len(faces),
            noisy_digest=smoothing_set.mesh_digest(noisy, faces),
        )
    weights = tmp_path / "milestone.msgpack"
    weights.write_bytes(b"a network")
    searched = []

    def fake_search(noisy, clean, faces, bundle, held):
        searched.append(bundle)
        return np.full((2, 2, 3), 2.0 + len(searched)), np.ones(2)

    monkeypatch.setattr(smoothing_set, "pass_errors", fake_search)
    monkeypatch.setattr(checkpoints, "load_model", lambda path: f"network of {path}")
    monkeypatch.setattr(dmd_jax, "denoise", lambda v, f, bundle: v)  # moves nothing
    assert smoothing_set.search_with(src, out, weights, sources=sources, say=print) == 2
    assert searched == [f"network of {weights}"] * 2
    data = smoothing_set.load(out)
    assert data["network"] == smoothing_set.network_digest(weights)
    assert smoothing_set.load(src)["network"] == smoothing_set.BUNDLED_NETWORK
    np.testing.assert_array_equal(data["errors"][:, 0, 0, 0], [3.0, 4.0])
    np.testing.assert_array_equal(data["features"], smoothing_set.load(src)["features"])
    for k, (noisy, clean, faces) in enumerate(noisy_meshes):
        noisy_error = np.mean(face_normal_errors_deg(noisy, clean, faces))
        assert data["default_error"][k] == pytest.approx(noisy_error)
    # Resumes: nothing left to do.
    assert smoothing_set.search_with(src, out, weights, sources=sources) == 0
    # Another network into the same folder is refused; so is a mixed set.
    other = tmp_path / "other.msgpack"
    other.write_bytes(b"another network")
    with pytest.raises(ValueError, match="another source or network"):
        smoothing_set.search_with(src, out, other, sources=sources)
    shutil.copy(src / "examples" / "00000.npz", out / "examples" / "00002.npz")
    with pytest.raises(ValueError, match="mixes searches of several networks"):
        smoothing_set.load(out)


def test_a_set_built_for_another_network_is_the_set_searched_again_for_it(tmp_path, monkeypatch):
    """`build(network=W)` writes what `build` then `search_with(W)` write: the same
    examples, statistics and specs, searched for W, its digest in every example."""
    import dmd_jax
    from dmd_jax import checkpoints

    def fake_search(noisy, clean, faces, bundle, held):  # the network's name and the mesh
        return np.full((2, 2, 3), len(str(bundle)) + float(noisy.sum())), np.ones(2)

    monkeypatch.setattr(smoothing_set, "pass_errors", fake_search)
    monkeypatch.setattr(checkpoints, "load_model", lambda path: f"network of {path}")
    monkeypatch.setattr(dmd_jax, "denoise", lambda v, f, bundle: v)
    weights = tmp_path / "milestone.msgpack"
    weights.write_bytes(b"a network")
    sources, quiet = OneBall(), lambda *a: None
    bundled, searched, built = tmp_path / "bundled", tmp_path / "searched", tmp_path / "built"
    n = smoothing_set.build(bundled, 3, sources=sources, bundle="bundled", say=quiet)
    assert n >= 2
    smoothing_set.search_with(bundled, searched, weights, sources=sources, say=quiet)
    assert smoothing_set.build(built, 3, sources=sources, network=weights, say=quiet) == n
    a, b = smoothing_set.load(searched), smoothing_set.load(built)
    assert b["network"] == a["network"] == smoothing_set.network_digest(weights)
    assert b["specs"] == a["specs"]
    for key in ("features", "errors", "first_pass", "default_error", "crop_features"):
        np.testing.assert_array_equal(b[key], a[key])
    assert not np.array_equal(b["errors"], smoothing_set.load(bundled)["errors"])
    assert json.loads((built / "manifest.json").read_text())["network"] == b["network"]
    # A build for another network into the same folder is refused.
    other = tmp_path / "other.msgpack"
    other.write_bytes(b"another network")
    with pytest.raises(ValueError, match="other settings"):
        smoothing_set.build(built, 4, sources=sources, network=other, say=quiet)


def controller_features_version():
    from dmd_jax.controller_features import FEATURES_VERSION

    return FEATURES_VERSION


def test_example_specs_are_pure_and_cover_every_kind():
    counts = {"procedural": 50, "real": 40, "stress": 8}
    specs = [smoothing_set.example_spec(0, i, counts) for i in range(400)]
    assert specs == [smoothing_set.example_spec(0, i, counts) for i in range(400)]
    assert {s["kind"] for s in specs} == set(smoothing_set.KINDS)
    assert {s["source"] for s in specs} == set(counts)
    json.dumps(specs)  # stored with each example
    scanners = [s for s in specs if s["kind"] in ("scanner", "scan")]
    lengths = [s["correlation_length"] for s in scanners]
    assert min(lengths) < 3 and max(lengths) > 12  # the scanner model varied widely
    # The first build's examples (below TRIANGULATION_FROM) regenerate as they were
    # searched: no triangulation field; later ones draw every re-triangulation.
    assert all("triangulation" not in s for s in specs)
    first = smoothing_set.TRIANGULATION_FROM
    later = [smoothing_set.example_spec(0, i, counts) for i in range(first, first + 400)]
    assert {s["triangulation"]["kind"] for s in later} == set(smoothing_set.TRIANGULATIONS)
    assert all(s["triangulation"]["kind"] == "given" for s in later if s["kind"] == "scan")
    # The new draws come from a stream of their own: the rest of a spec is unchanged.
    same = smoothing_set.example_spec(0, first, counts)
    del same["triangulation"]
    assert same == {k: v for k, v in later[0].items() if k != "triangulation"}


def test_whole_mesh_examples_draw_validation_sizes_from_a_stream_of_their_own():
    counts = {"procedural": 50, "real": 40, "stress": 8}
    first = smoothing_set.WHOLE_FROM
    specs = [smoothing_set.example_spec(0, i, counts) for i in range(first, first + 200)]
    lo, hi = smoothing_set.WHOLE_FACES
    sizes = np.array([s["patch_faces"] for s in specs])
    assert all(s["whole"] for s in specs) and sizes.min() >= lo and sizes.max() <= hi
    assert sizes.min() < 3_000 and sizes.max() > 10_000  # the range is covered
    assert {s["kind"] for s in specs} == set(smoothing_set.KINDS)
    below = smoothing_set.example_spec(0, first - 1, counts)
    assert "whole" not in below and below["patch_faces"] <= smoothing_set.PATCH_FACES[1]
    # Only the size is drawn anew: the rest of the spec is what the index draws anyway.
    a = smoothing_set.example_spec(0, first, counts)
    rng_draws = {k: v for k, v in a.items() if k not in ("patch_faces", "whole")}
    assert rng_draws["index"] == first and rng_draws["kind"] in smoothing_set.KINDS


def test_a_mesh_read_in_crops_trains_as_it_is_read():
    """`fit` on `[n, C, F]` statistics learns the scores' mean over a mesh's real crops,
    as `decide` reads a large mesh: repeated crops change nothing, masked ones are
    ignored, and a choice that only the crops' mean reveals is learned."""
    rng = np.random.default_rng(1)
    n = 300
    feats = rng.standard_normal((n, 2))
    errors = rng.uniform(1.0, 3.0, (n, 3))
    opts = [
        controller.Option(0, None, 0),
        controller.Option(0, "jacobi", 1),
        controller.Option(0, "jacobi", 2),
    ]
    one = controller.fit(feats, errors, opts, hidden=6, steps=200, objective="regret")
    three = controller.fit(
        np.repeat(feats[:, None], 3, axis=1), errors, opts, hidden=6, steps=200, objective="regret"
    )
    np.testing.assert_allclose(three.w2, one.w2, rtol=1e-4, atol=1e-6)
    padded = np.concatenate([feats[:, None], rng.normal(50.0, 9.0, (n, 2, 2))], axis=1)
    mask = np.zeros((n, 3), bool)
    mask[:, 0] = True
    masked = controller.fit(
        padded, errors, opts, hidden=6, steps=200, objective="regret", crop_mask=mask
    )
    np.testing.assert_allclose(masked.w2, one.w2, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(
        controller.crop_scores(masked, padded, mask), controller.scores(one, feats), atol=1e-4
    )
    # Two crops each: option 1 is best where the crops' first statistics sum above 0,
    # which neither crop shows alone.
    crops = rng.standard_normal((n, 2, 2))
    best = np.where(crops[:, :, 0].sum(axis=1) > 0, 1, 2)
    errors = np.full((n, 3), 6.0)
    errors[np.arange(n), best] = 2.0
    fitted = controller.fit(
        crops, errors, opts, hidden=8, steps=800, objective="regret", kind="identity"
    )
    chosen = np.argmax(controller.crop_scores(fitted, crops), axis=1)
    assert np.mean(chosen == best) > 0.9
    with pytest.raises(ValueError, match="crop mask"):
        controller.fit(padded, errors, opts, crop_mask=np.zeros((n, 3), bool))


def test_stale_statistics_are_refused_and_recomputed(tmp_path, monkeypatch):
    """An example whose statistics are of another version is refused by `load` and
    recomputed by `refeature` from its regenerated mesh (the search kept); one whose
    regenerated mesh is not the one searched is moved aside."""
    from dmd_jax import controller_features

    sources = OneBall()
    v, f = sources.ball
    (tmp_path / "examples").mkdir()
    (tmp_path / "manifest.json").write_text(json.dumps({"sources": sources.counts()}))
    errors = np.arange(2 * 2 * 3, dtype=np.float64).reshape(2, 2, 3)
    for i, n_faces in ((0, len(f)), (1, len(f) + 1)):
        spec = {
            "index": i,
            "source": "stress",
            "mesh": 0,
            "kind": "gaussian_normal",
            "level": 0.2,
            "noise_seed": i,
        }
        np.savez(
            tmp_path / "examples" / f"{i:05d}.npz",
            features=np.zeros(3),
            errors=errors,
            first_pass=np.zeros(2),
            default_error=1.0,
            spec=json.dumps(spec),
            n_faces=n_faces,
            search_version=smoothing_set.SEARCH_VERSION,
        )  # no features_version: the first statistics
    with pytest.raises(ValueError, match="--refeature"):
        smoothing_set.load(tmp_path)
    report = smoothing_set.refeature(tmp_path, sources=sources, say=lambda _: None)
    assert report["rewritten"] == 1 and report["rejected"] == ["00001.npz"]
    data = smoothing_set.load(tmp_path)
    spec = data["specs"][0]
    _, noisy, _ = smoothing_set.noisy_example(spec, v, f)
    np.testing.assert_array_equal(data["features"][0], features(noisy, f))
    np.testing.assert_array_equal(data["errors"][0], errors)
    # Stored without crops (a small crop): read whole, one crop.
    assert data["crop_mask"].tolist() == [[True]]
    np.testing.assert_array_equal(data["crop_features"][0, 0], data["features"][0])
    # A whole mesh's crops are what `decide` reads of it.
    big_v, big_f = icosphere(4)
    stats = smoothing_set.crop_statistics(big_v, big_f)
    assert stats.shape == (controller_features.CROPS, controller_features.N_FEATURES)
    pieces = controller_features.crops(np.asarray(big_v, np.float64), np.asarray(big_f))
    np.testing.assert_allclose(stats[0], features(*pieces[0]))
    assert (tmp_path / "rejected" / "00001.npz").is_file()
    # Now current, with a digest: nothing to do; a new version makes it stale again.
    assert smoothing_set.refeature(tmp_path, sources=sources)["rewritten"] == 0
    monkeypatch.setattr(controller_features, "FEATURES_VERSION", 99)
    with pytest.raises(ValueError, match="another version"):
        smoothing_set.load(tmp_path)
    assert smoothing_set.refeature(tmp_path, sources=sources)["digest_checked"] == 1


def test_a_set_of_the_first_build_takes_the_new_manifest_fields(tmp_path):
    manifest = {"seed": 0, "sources": {"stress": 1}, "kinds": smoothing_set.KINDS}
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    smoothing_set.check_manifest(
        tmp_path, {**manifest, "triangulations": {}, "triangulation_from": 5}
    )
    with pytest.raises(ValueError, match="other settings"):
        smoothing_set.check_manifest(tmp_path, {**manifest, "seed": 1})


def test_a_fit_learns_a_choice_that_depends_on_the_statistics():
    """Two kinds of example: on one option 1 is best, on the other option 2; the
    statistic tells them apart. The controller learns to pick per example."""
    rng = np.random.default_rng(0)
    n = 400
    kind = rng.integers(2, size=n)
    feats = np.stack([kind + 0.1 * rng.standard_normal(n), rng.standard_normal(n)], axis=1)
    errors = np.full((n, 3), 10.0)
    errors[kind == 0, 1] = 2.0
    errors[kind == 1, 2] = 2.0
    opts = [
        controller.Option(0, None, 0),
        controller.Option(0, "jacobi", 1),
        controller.Option(0, "solve", 1),
    ]
    params = controller.fit(feats, errors, opts, hidden=8, steps=500, seed=0)
    chosen = np.argmax(controller.scores(params, feats), axis=1)
    assert np.mean(chosen == kind + 1) > 0.98
    r = controller.evaluate(chosen, errors, np.full(n, 10.0))
    assert r["to_oracle"] < 1.01 and r["capture"] > 0.95
    again = controller.fit(feats, errors, opts, hidden=8, steps=500, seed=0)
    np.testing.assert_array_equal(again.w2, params.w2)  # reproducible
    # Regressing each option's regret learns the same choice.
    reg = controller.fit(feats, errors, opts, hidden=8, steps=500, seed=0, objective="regret")
    assert np.mean(np.argmax(controller.scores(reg, feats), axis=1) == kind + 1) > 0.98
    back = controller.ControllerParams.from_dict(params.to_dict())
    assert back.options == params.options
    assert controller.choose(back, feats[0]) == params.options[int(chosen[0])]


def test_malformed_controller_sections_are_refused():
    opts = [controller.Option(0, None, 0)]
    good = controller.fit(np.zeros((4, 2)), np.ones((4, 1)), opts, hidden=2, steps=2).to_dict()
    for broken in (
        {k: v for k, v in good.items() if k != "w1"},
        {**good, "b2": np.zeros(5)},
        {**good, "w1": np.full_like(good["w1"], np.nan)},
        {**good, "options": [[0, "", "x"]]},
        {**good, "transform": "sqrt"},
    ):
        with pytest.raises(ValueError, match="controller section"):
            controller.ControllerParams.from_dict(broken)


def test_the_statistics_transform_is_stored_and_read():
    """A controller reads its statistics through the transform it was trained with; one
    stored before the field existed reads them as computed."""
    rng = np.random.default_rng(0)
    feats = np.abs(rng.standard_normal((50, 3))) * [1.0, 30.0, 0.1]
    opts = [controller.Option(0, None, 0), controller.Option(0, "jacobi", 1)]
    errors = rng.uniform(1.0, 2.0, (50, 2))
    params = controller.fit(feats, errors, opts, hidden=4, steps=20)
    assert params.transform == "log1p"
    np.testing.assert_allclose(params.mean, np.log1p(feats).mean(axis=0))
    back = controller.ControllerParams.from_dict(params.to_json())
    assert back.transform == "log1p"
    np.testing.assert_allclose(
        controller.scores(back, feats), controller.scores(params, feats), rtol=1e-5, atol=1e-5
    )
    old = {k: v for k, v in params.to_dict().items() if k != "transform"}
    assert controller.ControllerParams.from_dict(old).transform == "identity"


def _always(option, opts, n_feat=N_FEATURES):
    """A controller that picks `option` whatever it reads."""
    b2 = np.zeros(len(opts))
    b2[opts.index(option)] = 10.0
    return controller.ControllerParams(
        mean=np.zeros(n_feat),
        scale=np.ones(n_feat),
        w1=np.zeros((n_feat, 2)),
        b1=np.zeros(2),
        w2=np.zeros((2, len(opts))),
        b2=b2,
        options=tuple(opts),
    )


def test_denoise_runs_what_the_controller_chooses(sphere, tmp_path):
    v, f = sphere
    noisy = add_noise(5, v, f, "gaussian", 0.3, units="edge", direction="normal")
    bundle = rules_only(load_pretrained())
    opts = controller.options((0, 3), ("jacobi", "solve"), 3)
    pick = controller.Option(3, "solve", 2)
    stored = bundle._replace(controller=_always(pick, opts))  # stored, off by default
    with_ctrl = stored._replace(policy=stored.policy.replace(controller=True))
    np.testing.assert_array_equal(denoise(noisy, f, stored), denoise(noisy, f, bundle))
    np.testing.assert_array_equal(
        denoise(noisy, f, stored, controller=True), denoise(noisy, f, with_ctrl)
    )
    out, info = denoise(noisy, f, with_ctrl, return_info=True)
    solve = bundle.with_vertex_update("solve")
    np.testing.assert_array_equal(out, denoise(noisy, f, solve, presmooth=3, iterations=2))
    assert info.passes == 2 and info.presmooth_steps == 3
    assert info.controller.startswith("controller: 3 pre-smoothing steps, 2 passes (solve")
    # None: the mesh as given; pre-smoothing alone: no network pass.
    none = bundle._replace(controller=_always(controller.Option(0, None, 0), opts))
    out, info = denoise(noisy, f, none, controller=True, return_info=True)
    np.testing.assert_array_equal(out, noisy)
    assert (
        info.path == "no network"
        and info.passes == 0
        and "none (the mesh as given)" in info.controller
    )
    # The caller's choices win; controller=False ignores it; True needs one.
    np.testing.assert_array_equal(
        denoise(noisy, f, with_ctrl, iterations=1), denoise(noisy, f, bundle, iterations=1)
    )
    np.testing.assert_array_equal(
        denoise(noisy, f, with_ctrl, controller=False), denoise(noisy, f, bundle)
    )
    with pytest.raises(ValueError, match="hold no smoothing controller"):
        denoise(noisy, f, bundle, controller=True)
    with pytest.raises(ValueError, match="controller must be True, False or None"):
        denoise(noisy, f, bundle, controller="yes")


def test_the_controller_travels_in_the_weights_file(tmp_path):
    from dmd_jax import cli
    from dmd_jax.checkpoints import load_weights, pretrained_path

    opts = controller.options((0, 3), ("jacobi", "solve"), 3)
    params = _always(controller.Option(3, "jacobi", 1), opts)
    np.savez(tmp_path / "c.npz", **params.to_dict())
    out = tmp_path / "w.msgpack"
    assert (
        cli.main(
            [
                "export-weights",
                str(pretrained_path()),
                "-o",
                str(out),
                "--controller",
                str(tmp_path / "c.npz"),
            ]
        )
        == 0
    )
    back = load_weights(out).controller
    # Stored with the base's switch (`--controller-default` sets it).
    switch = load_weights(pretrained_path()).policy.controller
    assert back.options == params.options and load_weights(out).policy.controller == switch
    off = tmp_path / "off.msgpack"
    args = ["export-weights", str(out), "-o", str(off), "--controller-default", "off"]
    assert cli.main(args) == 0 and not load_weights(off).policy.controller
    on = tmp_path / "on.msgpack"
    args = ["export-weights", str(out), "-o", str(on), "--controller-default", "on"]
    assert cli.main(args) == 0 and load_weights(on).policy.controller
    np.testing.assert_allclose(back.b2, params.b2)
    (tmp_path / "bad.npz").write_bytes(b"nope")
    assert (
        cli.main(
            [
                "export-weights",
                str(pretrained_path()),
                "-o",
                str(tmp_path / "x.msgpack"),
                "--controller",
                str(tmp_path / "bad.npz"),
            ]
        )
        == 2
    )


def test_warmup_compiles_every_update_a_default_call_may_run(monkeypatch, tmp_path):
    """A controller whose options run the Jacobi update beside a config of the solve (or
    the other way round) needs two programs per rung: `dmd-jax warmup` compiles both."""
    from dmd_jax import compile_cache, forward, memory_plan, warmup

    bundle = rules_only(load_pretrained())
    own = bundle.config.model.vertex_update
    opts = controller.options((0, 3), ("jacobi", "solve"), 3)
    stored = bundle._replace(controller=_always(controller.Option(0, "jacobi", 1), opts))
    on = stored._replace(policy=stored.policy.replace(controller=True))
    assert bundle.vertex_updates() == stored.vertex_updates() == (own,)  # off: the config's
    assert on.vertex_updates()[0] == own and set(on.vertex_updates()) == {"jacobi", "solve"}
    only_none = controller.options((0,), (None,), 0)  # never runs the network
    assert on._replace(controller=_always(only_none[0], only_none)).vertex_updates() == (own,)

    prepared = []

    class Program:
        def __init__(self, config):
            self.update = config.model.vertex_update

        def prepare(self, params, noisy, graph):
            prepared.append((noisy.shape[0], self.update))
            return "compiled"

    monkeypatch.setenv(compile_cache.ENV, str(tmp_path))
    monkeypatch.setattr(forward, "predictor", Program)
    monkeypatch.setattr(memory_plan, "network_bytes_per_vertex", lambda model: None)
    done = warmup.warm_up(on, min_faces=1000, max_faces=3000)
    rungs = sorted({w.rung for w in done})
    assert len(rungs) >= 2 and len(done) == 2 * len(rungs)
    assert sorted(prepared) == sorted((r, u) for r in rungs for u in ("jacobi", "solve"))
    assert {(w.rung, w.update) for w in done} == set(prepared)


def test_a_large_mesh_is_read_in_crops_of_the_training_size():
    from dmd_jax.controller_features import CROP_VERTICES, CROPS, crops

    v, f = icosphere(5)  # 10,242 vertices
    v, f = np.asarray(v, np.float64), np.asarray(f, np.int64)
    noisy = add_noise(2, v, f, "gaussian", 0.2, units="edge", direction="normal")
    pieces = crops(noisy, f)
    assert len(pieces) == CROPS
    for pv, pf in pieces:
        assert len(pv) <= CROP_VERTICES and 400 <= len(pf) <= 1200  # the training crops' range
        assert pf.min() == 0 and pf.max() == len(pv) - 1
    again = crops(noisy, f)
    assert all(np.array_equal(a[1], b[1]) for a, b in zip(pieces, again, strict=True))
    # Homogeneous noise: each crop reads the whole mesh's roughness.
    whole = features(noisy, f)[FEATURE_NAMES.index("rough_q50")]
    for pv, pf in pieces:
        assert features(pv, pf)[FEATURE_NAMES.index("rough_q50")] == pytest.approx(whole, rel=0.15)
    small_v, small_f = icosphere(2)
    assert len(crops(small_v, small_f)) == 1  # read whole


def test_heavy_noise_examples_draw_the_papers_kinds_beyond_the_other_kinds_levels():
    counts = {"procedural": 50, "real": 40, "stress": 8}
    first = smoothing_set.HEAVY_FROM
    specs = [smoothing_set.example_spec(0, i, counts) for i in range(first, first + 200)]
    assert specs == [smoothing_set.example_spec(0, i, counts) for i in range(first, first + 200)]
    assert all(s["kind"] == "heavy" for s in specs)
    assert {s["noise"] for s in specs} == set(smoothing_set.HEAVY_KINDS)
    levels = np.array([s["level"] for s in specs])
    lo, hi = smoothing_set.HEAVY_LEVELS
    assert levels.min() >= lo and levels.max() <= hi and levels.min() < 0.8 and levels.max() > 2.2
    assert all("whole" not in s and "triangulation" not in s for s in specs)
    assert all(s["patch_faces"] <= smoothing_set.PATCH_FACES[1] for s in specs)
    below = smoothing_set.example_spec(0, first - 1, counts)
    assert below["kind"] != "heavy"
    # The noise it names is drawn, per coordinate, at that level.
    from conftest import icosphere

    v, f = icosphere(2)
    spec = {**specs[0], "noise_seed": 3}
    clean, noisy, faces = smoothing_set.noisy_example(spec, v, f)
    assert clean is v and faces is f and np.all(np.isfinite(noisy))
    edge = np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1).mean()
    move = np.linalg.norm(noisy - v, axis=1)
    assert move.mean() > 0.3 * spec["level"] * edge

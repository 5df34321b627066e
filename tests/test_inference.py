"""`denoise` and the weights files: equivariance, iterations, dtypes, padding, bad files.

One tiny `test`-preset model for the whole module (`tiny_params`), with a small random
denoiser head: the network moves vertices by a few hundredths of the mesh size, so the
equivariance tests compare non-trivial outputs.
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import icosphere

from dmd_jax import checkpoints
from dmd_jax.checkpoints import load_weights, save_weights
from dmd_jax.config import preset
from dmd_jax.graph import build_mesh_graph
from dmd_jax.inference import denoise
from dmd_jax.model import DMDNet, param_shapes

HEAD_SCALE = 1e-3  # head kernel std: vertex offsets of a few hundredths on a unit sphere


def tiny_params(seed: int = 0):
    """`test`-preset params: LeCun-normal kernels, zero biases, a small denoiser head.

    Drawn with NumPy on the shapes of `param_shapes` (an eager Flax init costs about 8 s
    of CPU here). The model's own init zeroes the denoiser head, which makes it the
    identity; a small random head makes outputs differ from inputs.
    """
    rng = np.random.default_rng(seed)

    def leaf(path, shape):
        name = jax.tree_util.keystr(path)
        if name.endswith("['bias']"):
            return np.zeros(shape.shape, np.float32)
        std = HEAD_SCALE if name == "['denoiser']['stack']['head']['kernel']" else 1.0
        std /= np.sqrt(shape.shape[0])
        return (std * rng.standard_normal(shape.shape)).astype(np.float32)

    return jax.tree_util.tree_map_with_path(leaf, param_shapes(TINY_CONFIG.model))


# The paper's encoding and offset head (the `test` preset before it became the small
# recipe): the checks below compare with a hand-applied bounding-box frame and name the
# offset head's parameters.
TINY_CONFIG = preset("test").with_edits({"model": {"encoding": "xyz", "head": "offset"}})


@pytest.fixture(scope="module")
def weights_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("weights") / "tiny.msgpack"
    save_weights(path, tiny_params(), TINY_CONFIG, {"note": "tiny test model"})
    return path


@pytest.fixture(scope="module")
def bundle(weights_path):
    return load_weights(weights_path)


@pytest.fixture(scope="module")
def mesh():
    # One mesh size for the whole module, so `denoise` compiles once.
    return icosphere(2)


@pytest.fixture(scope="module")
def reference(mesh, bundle):
    v, f = mesh
    return denoise(v, f, bundle)


def test_network_moves_vertices(mesh, reference):
    v, _ = mesh
    moved = np.linalg.norm(reference - v, axis=1)
    assert reference.dtype == np.float64 and reference.shape == v.shape
    assert 1e-3 < moved.mean() < 0.2


def _unpadded_reference(bundle, v, f, iterations=1):
    """Independent path: the model on the unpadded graph, the frame applied by hand."""
    lo, hi = v.min(0), v.max(0)
    centre, scale = (lo + hi) / 2, (hi - lo).max()
    x = jnp.asarray((v - centre) / scale, jnp.float32)
    graph = jax.tree.map(jnp.asarray, build_mesh_graph(f, len(v)))
    model = DMDNet(bundle.config.model)
    apply = jax.jit(lambda p, x, g: model.apply({"params": p}, x, g, deterministic=True)[0])
    for _ in range(iterations):
        x = apply(bundle.params, x, graph)
    return np.asarray(x, np.float64) * scale + centre, scale


def test_matches_unpadded_model_in_canonical_frame(mesh, bundle, reference):
    # Agreement shows that bucketed padding is masked out and the frame inverted exactly.
    v, f = mesh
    expected, scale = _unpadded_reference(bundle, v, f)
    np.testing.assert_allclose(reference, expected, atol=1e-5 * scale)
    twice, _ = _unpadded_reference(bundle, v, f, iterations=2)
    # Each pass starts from the last one, in the canonical frame of the input.
    np.testing.assert_allclose(denoise(v, f, bundle, iterations=2), twice, atol=1e-5 * scale)
    assert np.abs(twice - reference).max() > 1e-3


def test_a_higher_rung_changes_nothing(mesh, bundle, reference, monkeypatch):
    # A rung's padding rows are masked out: the mesh run on the next rung up (other
    # shapes, another program) gives the same result.
    from dmd_jax import inference, shape_ladder

    v, f = mesh
    own = shape_ladder.padded_sizes(inference.build_mesh_graph(f, len(v)))
    higher = shape_ladder.rung_sizes(shape_ladder.rung_above(own.n_vertex + 1))
    monkeypatch.setattr(shape_ladder, "padded_sizes", lambda graph: higher)
    assert inference.whole_mesh_graph(f, len(v), "auto").n_vertex == higher.n_vertex
    np.testing.assert_allclose(denoise(v, f, bundle), reference, atol=1e-5)


def test_pass_tolerance_repeats_passes_while_they_move_the_mesh(mesh, bundle, reference):
    from dmd_jax.policy import DenoisePolicy

    v, f = mesh
    # The default policy (a weights file saved without one): one pass.
    out, info = denoise(v, f, bundle, return_info=True)
    np.testing.assert_array_equal(out, reference)
    assert info.passes == 1 and info.policy == DenoisePolicy()
    moves = []
    x = v
    for _ in range(2):
        y = denoise(x, f, bundle, iterations=1)
        moves.append(np.linalg.norm(y - x, axis=1).mean() / (v.max(0) - v.min(0)).max())
        x = y
    # Passes run while the last one moved the mesh more than the tolerance (bounding-box
    # units for this model's frame): above the first move, one pass; between the first
    # and the second, two; a tiny tolerance, the most allowed.
    mid = (moves[0] + moves[1]) / 2
    assert moves[1] < mid < moves[0]
    for tolerance, passes in ((moves[0] * 1.01, 1), (mid, 2), (1e-12, 5)):
        policy = DenoisePolicy(max_passes=5, pass_tolerance=float(tolerance))
        out, info = denoise(v, f, bundle, policy=policy, return_info=True)
        assert info.passes == passes
        np.testing.assert_allclose(out, denoise(v, f, bundle, iterations=passes), atol=1e-6)
    # The patch-by-patch path follows the same rule; a policy stored in the bundle is the
    # default.
    policy = DenoisePolicy(max_passes=8, pass_tolerance=float(mid))
    out, info = denoise(v, f, bundle._replace(policy=policy), patch_size=60, return_info=True)
    assert info.path == "patches" and info.passes == 2 and info.policy == policy
    np.testing.assert_allclose(out, denoise(v, f, bundle, iterations=2), atol=1e-4)
    # A fixed iteration count overrides the rule.
    _, info = denoise(v, f, bundle._replace(policy=policy), iterations=3, return_info=True)
    assert info.passes == 3 and info.policy.pass_tolerance == 0
    for bad in (0, -1, 1.5, True, "2", 10**9, float("inf")):
        with pytest.raises(ValueError, match="iterations must be a whole number from 1 to 64"):
            denoise(v, f, bundle, iterations=bad)


@pytest.mark.parametrize("shift", [(5.0, -3.0, 1e3), (-1e-3, 2e-3, 0.0)])
def test_translation_equivariance(mesh, bundle, reference, shift):
    v, f = mesh
    t = np.asarray(shift)
    out = denoise(v + t, f, bundle)
    # Float32 inside: the canonical coordinates of v + t differ from those of v by
    # rounding of |t| / scale, about 1e-7 relative for |t| = 1e3, scale 2.
    np.testing.assert_allclose(out - t, reference, atol=2e-5)


@pytest.mark.parametrize("factor", [1e-3, 7.5, 1e4])
def test_scale_equivariance(mesh, bundle, reference, factor):
    v, f = mesh
    out = denoise(v * factor, f, bundle)
    np.testing.assert_allclose(out / factor, reference, atol=1e-6)


def test_similarity_equivariance_about_a_point(mesh, bundle, reference):
    v, f = mesh
    c = np.array([0.3, -2.0, 0.7])
    out = denoise((v - c) * 0.01, f, bundle)
    np.testing.assert_allclose(out / 0.01 + c, reference, atol=1e-6)


@pytest.mark.parametrize("iterations", [0, -1])
def test_iterations_must_be_positive(mesh, bundle, iterations):
    v, f = mesh
    with pytest.raises(ValueError, match="iterations"):
        denoise(v, f, bundle, iterations=iterations)


def test_float32_in_float32_out(mesh, bundle, reference):
    v, f = mesh
    out = denoise(v.astype(np.float32), f, bundle)
    assert out.dtype == np.float32 and out.shape == v.shape
    np.testing.assert_allclose(out, reference, atol=1e-5)


@pytest.mark.parametrize("dtype", [np.float16, np.int64])
def test_other_vertex_dtypes_give_float64(bundle, dtype):
    # Integer coordinates (a voxel grid, say) and float16 are read as float64.
    v, f = icosphere(2)
    v = np.round(v * 100).astype(dtype)
    out = denoise(v, f, bundle)
    assert out.dtype == np.float64
    expected = denoise(v.astype(np.float64), f, bundle)
    np.testing.assert_allclose(out, expected, atol=1e-9)


@pytest.mark.parametrize("face_dtype", [np.int64, np.uint32, np.int16])
def test_face_dtypes(mesh, bundle, reference, face_dtype):
    v, f = mesh
    np.testing.assert_array_equal(denoise(v, f.astype(face_dtype), bundle), reference)


def test_jax_array_inputs(mesh, bundle, reference):
    v, f = mesh
    out = denoise(jnp.asarray(v), jnp.asarray(f), bundle)
    np.testing.assert_allclose(out, reference, atol=1e-5)


def test_bad_mesh_is_a_value_error(bundle):
    v, f = icosphere(2)
    with pytest.raises(ValueError, match="out of range"):
        denoise(v, f + len(v), bundle)
    v_nan = v.copy()
    v_nan[3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        denoise(v_nan, f, bundle)


def test_params_forms(mesh, bundle, weights_path, reference):
    v, f = mesh
    np.testing.assert_array_equal(denoise(v, f, str(weights_path)), reference)
    np.testing.assert_array_equal(denoise(v, f, bundle.params, config=bundle.config), reference)
    with pytest.raises(ValueError, match="config"):
        denoise(v, f, bundle.params)


def test_save_load_round_trip(weights_path, bundle, tmp_path):
    expected = tiny_params()
    for path, x in jax.tree_util.tree_flatten_with_path(expected)[0]:
        got = bundle.params
        for k in path:
            got = got[k.key]
        np.testing.assert_array_equal(got, x)
    assert bundle.config == TINY_CONFIG
    assert bundle.meta == {"note": "tiny test model"}
    with pytest.raises(FileExistsError):
        save_weights(weights_path, bundle.params, bundle.config)
    copy = save_weights(tmp_path / "copy.msgpack", bundle.params, bundle.config, bundle.meta)
    assert copy.read_bytes() == weights_path.read_bytes()


def _payload(path) -> dict:
    from flax import serialization

    return serialization.msgpack_restore(path.read_bytes())


def _write_payload(path, payload):
    from flax import serialization

    path.write_bytes(serialization.msgpack_serialize(payload))
    return path


@pytest.mark.parametrize("cut", ["one byte", "ten bytes", "half", "all but one byte"])
def test_truncated_file(weights_path, tmp_path, cut):
    raw = weights_path.read_bytes()
    keep = {"one byte": 1, "ten bytes": 10, "half": len(raw) // 2, "all but one byte": -1}
    path = tmp_path / "truncated.msgpack"
    path.write_bytes(raw[: keep[cut]])
    with pytest.raises(ValueError, match="truncated or corrupt|not a dmd_jax"):
        load_weights(path)


def test_not_a_weights_file(tmp_path):
    npz = tmp_path / "weights.npz"
    np.savez(npz, a=np.zeros(3))
    with pytest.raises(ValueError):
        load_weights(npz)
    other = _write_payload(tmp_path / "other.msgpack", {"params": {"w": np.zeros(3)}})
    with pytest.raises(ValueError, match="not a dmd_jax weights file"):
        load_weights(other)
    empty = tmp_path / "empty.msgpack"
    empty.write_bytes(b"")
    with pytest.raises(ValueError):
        load_weights(empty)
    with pytest.raises(FileNotFoundError):
        load_weights(tmp_path / "missing.msgpack")


def test_other_format_version(weights_path, tmp_path):
    payload = _payload(weights_path)
    payload["version"] = checkpoints.WEIGHTS_VERSION + 1
    path = _write_payload(tmp_path / "v2.msgpack", payload)
    with pytest.raises(ValueError, match="version"):
        load_weights(path)


def test_config_mismatch(weights_path, tmp_path):
    # Params of the `test` preset stored with the `small` config: every width differs.
    payload = _payload(weights_path)
    payload["config"] = json.dumps(preset("small").to_dict())
    path = _write_payload(tmp_path / "mismatch.msgpack", payload)
    with pytest.raises(ValueError, match="do not match their config"):
        load_weights(path)
    # A missing parameter is named as missing.
    payload = _payload(weights_path)
    del payload["params"]["denoiser"]["stack"]["head"]["bias"]
    path = _write_payload(tmp_path / "missing_leaf.msgpack", payload)
    with pytest.raises(ValueError, match="missing"):
        load_weights(path)


def test_load_pretrained_reads_the_package_path(monkeypatch, weights_path, tmp_path):
    monkeypatch.setattr(checkpoints, "pretrained_path", lambda: weights_path)
    loaded = checkpoints.load_pretrained()
    assert loaded.config == TINY_CONFIG and loaded.meta["note"] == "tiny test model"
    monkeypatch.setattr(checkpoints, "pretrained_path", lambda: tmp_path / "absent.msgpack")
    with pytest.raises(FileNotFoundError, match="bundled weights are missing"):
        checkpoints.load_pretrained()


@pytest.mark.skipif(
    not checkpoints.pretrained_path().is_file(), reason="the bundled weights are not installed"
)
def test_bundled_model_reduces_normal_error():
    from dmd_jax.metrics import mesh_metrics
    from dmd_jax.protocol import benchmark_noise

    pretrained = checkpoints.load_pretrained()
    assert pretrained.config.name == "small"
    v, f = icosphere(3)
    noisy = benchmark_noise(v, f, 0.2, seed=0)
    out = denoise(noisy, f, pretrained)
    assert np.all(np.isfinite(out))
    before = mesh_metrics(noisy, v, f)["normal_deg"]
    after = mesh_metrics(out, v, f)["normal_deg"]
    assert after < 0.8 * before, (before, after)


def test_info_repr_is_a_short_summary_with_every_field_reachable():
    # Issue 55: printing the info in a notebook must not flood the page.
    import dataclasses

    import trimesh

    from dmd_jax.inference import INFO_REPR_MAX

    mesh = trimesh.creation.icosphere(3)
    out, info = denoise(mesh.vertices, mesh.faces, return_info=True)
    text = repr(info)
    assert len(text) <= 2000 and INFO_REPR_MAX <= 2000
    assert text.startswith(f"DenoiseInfo(path={info.path!r}, passes=")
    assert "presmooth_steps=" in text and "policy=DenoisePolicy(max_passes=" in text
    assert info.policy.max_passes >= 1 and info.patch_size is None  # fields as they are
    # Arrays show by shape, long sequences by length, and the whole stays bounded.
    wide = dataclasses.replace(info, devices=np.zeros((1000, 3)), patches=tuple(range(10**5)))
    text = repr(wide)
    assert "devices=array[1000, 3] float64" in text and "patches=<tuple of 100000>" in text
    assert wide.devices.shape == (1000, 3) and len(wide.patches) == 10**5
    long = dataclasses.replace(info, path="x" * 5000)
    assert len(repr(long)) == INFO_REPR_MAX and repr(long).endswith(" ...)")

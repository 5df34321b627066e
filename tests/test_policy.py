"""The denoising policy apart from the network: its home, the weights file's policy section,
old files, the overrides, the bounds, and `denoise`'s handling of unused vertices and of
meshes at any offset and scale (the frame comes from referenced vertices only)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import icosphere
from test_inference import TINY_CONFIG, tiny_params

import dmd_jax
from dmd_jax import checkpoints
from dmd_jax.config import LEGACY_POLICY_FIELDS, ModelConfig
from dmd_jax.inference import DenoiseInfo, denoise
from dmd_jax.policy import RETIRED_FIELDS, DenoisePolicy, RetiredPolicyWarning, run_passes

REFERENCE = Path(__file__).resolve().parent / "data" / "bundled_reference.npz"


@pytest.fixture(scope="module")
def reference():
    with np.load(REFERENCE) as data:
        return {k: data[k] for k in data.files}


@pytest.fixture(scope="module")
def bundled():
    return dmd_jax.load_pretrained()


def test_model_config_holds_no_inference_rule():
    names = {f.name for f in dataclasses.fields(ModelConfig)}
    rules = {f.name for f in dataclasses.fields(DenoisePolicy)}
    assert not names & (rules | set(LEGACY_POLICY_FIELDS))


def test_bundled_weights_carry_their_policy_in_format_2(bundled):
    payload = checkpoints.read_weights_payload(
        checkpoints.pretrained_path(), fmt=checkpoints.WEIGHTS_FORMAT, versions=(2,), kind="x"
    )
    stored = DenoisePolicy.from_dict(json.loads(payload["policy"]))
    assert stored == bundled.policy
    assert bundled.policy.pass_tolerance > 0 and bundled.policy.presmooth_start > 0


def _numbers(value) -> int:
    return len(value) if isinstance(value, list | tuple) else 1


def test_the_bundled_policy_is_a_few_rules_not_fitted_tables():
    # Issue 54: at most 6 fields and 16 numbers in all; no selector's table.
    policy = dmd_jax.load_pretrained().policy
    fields = policy.to_dict()
    assert len(dataclasses.fields(DenoisePolicy)) <= 6 and len(fields) <= 6
    assert sum(_numbers(v) for v in fields.values()) <= 16
    assert not set(fields) & set(RETIRED_FIELDS)


def _with_retired_fields(tmp_path, extra: dict) -> Path:
    """The bundled weights file rewritten as a file of before issue 54: its own bytes,
    the policy section carrying (small) selector fields beside its rules."""
    from flax import serialization

    payload = serialization.msgpack_restore(checkpoints.pretrained_path().read_bytes())
    policy = {**json.loads(payload["policy"]), **extra}
    path = tmp_path / "old_selectors.msgpack"
    path.write_bytes(serialization.msgpack_serialize({**payload, "policy": json.dumps(policy)}))
    return path


def test_weights_with_the_retired_selector_fields_load_with_one_warning(tmp_path, bundled):
    old = {
        "presmooth_grid": [0, 2],
        "presmooth_center": [0.0] * 11,
        "presmooth_scale": [1.0] * 11,
        "presmooth_examples": [0.5] * 22,
        "presmooth_regrets": [0.0, 1.0, 0.0, 1.0],
        "presmooth_neighbours": 1,
        "route_sigmas": [0.2],
        "route_passes": [60],
        "review_route": 0,
        "review_neighbours": 1,
        "cascade_sigmas": [0.2],
        "cascade_passes": [4],
    }
    path = _with_retired_fields(tmp_path, old)
    with pytest.warns(RetiredPolicyWarning) as caught:
        loaded = checkpoints.load_weights(path)
    assert len(caught) == 1
    message = str(caught[0].message)
    assert str(path) in message and all(name in message for name in old)
    assert loaded.policy == bundled.policy
    assert loaded.config == bundled.config
    v, f = icosphere(2)
    np.testing.assert_array_equal(denoise(v, f, loaded), denoise(v, f, bundled))
    # An unknown field that was never a selector's is still an error.
    bad = _with_retired_fields(tmp_path, {"presmooth_gird": [0, 2]})
    with pytest.raises(ValueError, match="unreadable policy"):
        checkpoints.load_weights(bad)


def _write_v1(path, model_extra: dict):
    """A weights file as format 1 wrote it: the rules inside the model config."""
    config = TINY_CONFIG.to_dict()
    config["model"] = {**config["model"], **model_extra}
    checkpoints.write_weights_file(
        path,
        fmt=checkpoints.WEIGHTS_FORMAT,
        version=1,
        config=config,
        meta={"v": 1},
        params=tiny_params(),
    )


def test_version_1_files_load_with_their_rules_as_policy(tmp_path):
    _write_v1(
        tmp_path / "old.msgpack",
        {"pass_tolerance": 0.25, "presmooth_start": 30.0, "presmooth_per_step": 4.0},
    )
    bundle = checkpoints.load_weights(tmp_path / "old.msgpack")
    assert bundle.config == TINY_CONFIG and bundle.meta == {"v": 1}
    assert bundle.policy == DenoisePolicy(
        max_passes=8, pass_tolerance=0.25, presmooth_start=30.0, presmooth_per_step=4.0
    )
    _write_v1(
        tmp_path / "plain.msgpack",
        {"pass_tolerance": 0.0, "presmooth_start": 0.0, "presmooth_per_step": 5.0},
    )
    assert checkpoints.load_weights(tmp_path / "plain.msgpack").policy == DenoisePolicy()
    # Re-saved, a version-1 file becomes version 2 with the same policy.
    old = checkpoints.load_weights(tmp_path / "old.msgpack")
    checkpoints.save_weights(tmp_path / "new.msgpack", old.params, old.config, policy=old.policy)
    assert checkpoints.load_weights(tmp_path / "new.msgpack").policy == old.policy


def test_bad_policy_sections_are_named(tmp_path):
    checkpoints.write_weights_file(
        tmp_path / "w.msgpack",
        fmt=checkpoints.WEIGHTS_FORMAT,
        version=2,
        config=TINY_CONFIG.to_dict(),
        meta={},
        params=tiny_params(),
        sections={"policy": {"max_passes": 10**7}},
    )
    with pytest.raises(ValueError, match="w.msgpack: unreadable policy .*max_passes must be at"):
        checkpoints.load_weights(tmp_path / "w.msgpack")
    checkpoints.write_weights_file(
        tmp_path / "n.msgpack",
        fmt=checkpoints.WEIGHTS_FORMAT,
        version=2,
        config=TINY_CONFIG.to_dict(),
        meta={},
        params=tiny_params(),
    )
    with pytest.raises(ValueError, match="n.msgpack: incomplete weights file .no policy"):
        checkpoints.load_weights(tmp_path / "n.msgpack")


@pytest.mark.parametrize(
    "edits, message",
    [
        ({"max_passes": 0}, "max_passes must be an integer >= 1"),
        ({"max_passes": 65}, "max_passes must be at most 64"),
        ({"pass_tolerance": -0.1}, "pass_tolerance must be a finite number >= 0"),
        ({"pass_tolerance": float("inf")}, "pass_tolerance: expected a finite number"),
        ({"presmooth_start": -1.0}, "presmooth_start must be a finite number >= 0"),
        ({"presmooth_start": 1e9}, "presmooth_start is a roughness in degrees"),
        ({"presmooth_per_step": 0.0}, "presmooth_per_step must be a finite number > 0"),
        ({"presmooth_per_step": 1e-300}, "presmooth_per_step must be at least 0.001"),
        ({"relax_steps": 10**30}, "relax_steps must be at most 1000"),
    ],
)
def test_policy_validation(edits, message):
    with pytest.raises(ValueError, match=message):
        DenoisePolicy().with_edits(edits)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"iterations": 10**30}, "iterations must be a whole number from 1 to 64"),
        ({"iterations": float("nan")}, "iterations must be a whole number"),
        ({"presmooth": 10**9}, "presmooth must be a whole number from 0 to 20"),
        ({"presmooth": float("inf")}, "presmooth must be a whole number"),
        ({"relax": 10**30}, "relax must be a whole number from 0 to 1000"),
        ({"relax": -1}, "relax must be a whole number"),
        ({"patch_size": 0}, "patch_size must be a whole number from 1"),
        ({"policy": {"max_passes": 2}}, "policy must be a DenoisePolicy"),
    ],
)
def test_every_count_is_bounded_before_any_work(reference, kwargs, message):
    with pytest.raises(ValueError, match=message):
        denoise(reference["vertices"], reference["faces"], **kwargs)


def test_run_passes_follows_the_policy():
    calls = []

    def halve(x):
        calls.append(1)
        return x / 2

    x = np.ones((4, 3))
    out, done = run_passes(halve, x, DenoisePolicy(max_passes=6))
    assert done == 6 and len(calls) == 6
    np.testing.assert_allclose(out, x / 64)
    # Moves are sqrt(3)/2, /4, /8 ...: a tolerance of 0.3 stops after the third.
    _, done = run_passes(halve, x, DenoisePolicy(max_passes=6, pass_tolerance=0.3))
    assert done == 3
    with pytest.raises(ValueError, match="non-finite vertices"):
        run_passes(lambda x: x * np.nan, x, DenoisePolicy())


def test_denoise_defaults_to_the_bundled_model_and_takes_a_trimesh(reference, bundled):
    import trimesh

    v, f = reference["vertices"], reference["faces"]
    expected = denoise(v, f, bundled)
    np.testing.assert_array_equal(dmd_jax.denoise(v, f), expected)
    mesh = trimesh.Trimesh(v, f, process=False)
    np.testing.assert_array_equal(dmd_jax.denoise(mesh), expected)
    np.testing.assert_array_equal(dmd_jax.denoise_with("dmd", mesh), expected)
    with pytest.raises(TypeError, match="pass denoise.vertices, faces. or a mesh object"):
        dmd_jax.denoise(v)


def test_info_says_how_the_call_ran(reference, bundled):
    v, f = reference["vertices"], reference["faces"]
    out, info = denoise(v, f, bundled, iterations=1, return_info=True)
    assert isinstance(info, DenoiseInfo)
    assert info.path == "whole" and info.patch_size is None and info.unused_vertices == 0
    assert info.policy == dataclasses.replace(bundled.policy, max_passes=1, pass_tolerance=0.0)
    assert info.passes == 1
    np.testing.assert_array_equal(out, denoise(v, f, bundled, iterations=1))
    # The bundled controller leaves this coarse (320 faces), lightly noisy sphere as
    # given (docs/controller.md, "Limits"); the info says so and from what.
    out, info = denoise(v, f, bundled, return_info=True)
    assert (info.path, info.passes, info.presmooth_steps) == ("no network", 0, 0)
    assert info.policy == bundled.policy
    assert info.controller.startswith("controller: none (the mesh as given); from roughness")
    np.testing.assert_array_equal(out, v)
    _, info = denoise(v, f, bundled, presmooth=2, relax=1, return_info=True)
    assert (info.presmooth_steps, info.roughness, info.relax_steps) == (2, None, 1)
    # presmooth="rule" is the policy's rule, as with no presmooth.
    from dmd_jax.presmooth import roughness, steps_for

    _, info = denoise(v, f, bundled, presmooth="rule", return_info=True)
    rough = roughness(v, f)
    policy = bundled.policy
    assert info.roughness == pytest.approx(rough)
    assert info.presmooth_steps == steps_for(
        rough, policy.presmooth_start, policy.presmooth_per_step
    )
    with pytest.raises(ValueError, match="presmooth must be a whole number"):
        denoise(v, f, presmooth="rules")


def test_unused_vertices_are_returned_exactly_and_change_nothing(reference, bundled):
    v, f = reference["vertices"], reference["faces"]
    expected = denoise(v, f, bundled)
    # Stray points: one far away, one at the origin, one near the mesh; put first, so
    # every face index shifts.
    stray = np.array([[1e8, -3e7, 5e6], [0.0, 0.0, 0.0], [0.01, 0.02, 0.03]])
    v2 = np.concatenate([stray, v])
    out, info = denoise(v2, f + len(stray), bundled, return_info=True)
    assert info.unused_vertices == 3
    np.testing.assert_array_equal(out[:3], stray)
    np.testing.assert_allclose(out[3:], expected, atol=1e-6)


@pytest.mark.parametrize("scale", [1e-150, 1e-40, 1e-16, 1e16, 1e150])
def test_any_scale_float64_holds_denoises_as_at_unit_scale(reference, bundled, scale):
    v, f = reference["vertices"].astype(np.float64), reference["faces"]
    expected = denoise(v, f, bundled)
    out = denoise(v * scale, f, bundled)
    assert np.all(np.isfinite(out))
    np.testing.assert_allclose(out / scale, expected, atol=1e-5)


@pytest.mark.parametrize("offset", [1e3, 5e5, 1e7])
def test_large_offsets_with_a_stray_vertex_denoise_as_at_the_origin(reference, bundled, offset):
    # Map-grid coordinates (x ~ 5e5, y ~ 4e6) plus one unused vertex at the origin: the
    # stray point must not enter the frame.
    v, f = reference["vertices"].astype(np.float64), reference["faces"]
    expected = denoise(v, f, bundled)
    shift = np.array([offset, 8.0 * offset, -offset])
    v2 = np.concatenate([v + shift, [[0.0, 0.0, 0.0]]])
    out = denoise(v2, f, bundled)
    np.testing.assert_array_equal(out[-1], [0.0, 0.0, 0.0])
    # float64 holds the offset to ~1e-16 relative: 1e-9 of an edge at 1e7.
    np.testing.assert_allclose(out[:-1] - shift, expected, atol=1e-5)


def test_a_run_trained_for_k_passes_is_run_for_k_passes():
    """Raw params with their config (as a checkpoint gives them) carry the policy their
    training implies: `TrainConfig.passes` passes, no tolerance, no pre-smoothing."""
    from dmd_jax.policy import DenoisePolicy, trained_policy

    cfg = TINY_CONFIG.with_edits({"train": {"passes": 3}})
    assert trained_policy(cfg) == DenoisePolicy(max_passes=3)
    bundle = checkpoints.as_bundle(tiny_params(), cfg)
    assert bundle.policy == DenoisePolicy(max_passes=3)
    assert checkpoints.as_bundle(tiny_params(), TINY_CONFIG).policy == DenoisePolicy()
    v, f = icosphere(2)
    _, info = dmd_jax.denoise(v, f, bundle, return_info=True)
    assert info.passes == 3


def test_the_model_card_states_the_bundled_file_sha():
    import hashlib
    import re

    card = (Path(__file__).resolve().parents[1] / "docs" / "bundled-model.md").read_text()
    (row,) = [line for line in card.splitlines() if line.startswith("| parameters |")]
    stated = re.search(r"SHA-256 `([0-9a-f]{12})`", row).group(1)
    digest = hashlib.sha256(checkpoints.pretrained_path().read_bytes()).hexdigest()
    assert digest.startswith(stated)

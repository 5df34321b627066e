"""The network-free routes of the learned choice (`dmd_jax.routes`): the host field and
vertex update against the encoding's JAX field and the head's JAX update, the frame,
the policy fields that carry them, their fit, and `denoise` taking one."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from test_policy import _learned_fields

from dmd_jax import calibrate as cal
from dmd_jax import encoding, geometry, routes
from dmd_jax.graph import build_mesh_graph
from dmd_jax.inference import denoise
from dmd_jax.mesh import mean_edge_length
from dmd_jax.metrics import mesh_metrics
from dmd_jax.policy import DenoisePolicy, presmooth_plan


def _noisy_box(level=0.1, seed=0):
    """A subdivided box (flats and sharp creases) with noise along the vertex normals,
    `level` mean edges; clean and noisy vertices, faces."""
    box = trimesh.creation.box().subdivide().subdivide().subdivide()
    v, f = np.asarray(box.vertices, np.float64), np.asarray(box.faces, np.int64)
    normals = np.asarray(box.vertex_normals)
    rng = np.random.default_rng(seed)
    h = mean_edge_length(v, f)
    return v, v + level * h * rng.standard_normal((len(v), 1)) * normals, f


def test_field_matches_the_encodings_jax_field():
    _, noisy, f = _noisy_box(0.2)
    x = (noisy - noisy.mean(0)) / mean_edge_length(noisy, f)
    graph = build_mesh_graph(f.astype(np.int32), len(x))
    n0 = geometry.face_normals(jnp.asarray(x), jnp.asarray(f, jnp.int32))
    for sigma, passes in ((0.2, 16), (0.35, 5)):
        want = encoding.bilateral_face_normals(
            jnp.asarray(x), graph, n0, sigma_r=sigma, iterations=passes
        )
        got = routes.field_normals(x, f, sigma, passes)
        np.testing.assert_allclose(got, np.asarray(want)[: len(f)], atol=2e-5)


def test_vertex_fit_matches_the_heads_jax_update():
    clean, noisy, f = _noisy_box(0.2)
    target = np.asarray(geometry.face_normals(jnp.asarray(clean), jnp.asarray(f, jnp.int32)))
    f32 = f.astype(np.int32)
    want = geometry.fit_vertices_to_normals(
        jnp.asarray(noisy),
        f32,
        jnp.asarray(target),
        f32.ravel(),
        np.repeat(np.arange(len(f)), 3).astype(np.int32),
        jnp.ones(len(noisy)),
        7,
    )
    got = routes.fit_vertices(noisy, f, target, 7)
    np.testing.assert_allclose(got, np.asarray(want), atol=1e-6)


def test_a_route_denoises_a_box_and_is_translation_and_scale_equivariant():
    clean, noisy, f = _noisy_box(0.1)
    out = routes.run_route(noisy, f, 0.2, 60)
    before = mesh_metrics(noisy, clean, f)["normal_deg"]
    after = mesh_metrics(out, clean, f)["normal_deg"]
    assert after < 0.3 * before
    moved = routes.run_route(3.0 * noisy + [10.0, -5.0, 2.0], f, 0.2, 60)
    np.testing.assert_allclose(moved, 3.0 * out + [10.0, -5.0, 2.0], atol=1e-9)
    # The input is not touched.
    np.testing.assert_array_equal(noisy, _noisy_box(0.1)[1])


def _route_fields(regrets_per_example, n_example=6, grid=(0, 1, 3)):
    """A learned choice over `grid` and two routes; every example has the same regrets."""
    fields = _learned_fields(n_example, grid)
    fields["presmooth_regrets"] = tuple(regrets_per_example) * n_example
    return {**fields, "route_sigmas": (0.2, 0.35), "route_passes": (60, 20)}


def _routed(regrets_per_example):
    return DenoisePolicy().with_edits(_route_fields(regrets_per_example))


@pytest.mark.parametrize(
    "edits, message",
    [
        ({"route_passes": (60,)}, "route_sigmas and route_passes must pair up"),
        ({"route_sigmas": (0.0, 0.35)}, "route_sigmas must be range sigmas"),
        ({"route_sigmas": (float("nan"), 0.35)}, "route_sigmas: expected a finite"),
        ({"route_passes": (60, 10_000)}, "route_passes must be whole numbers from 1 to 500"),
        ({"route_passes": (60, 0)}, "route_passes must be whole numbers"),
        ({"presmooth_regrets": (0.1,) * 18}, "presmooth_regrets must hold 30 finite numbers"),
    ],
)
def test_route_fields_are_checked_before_use(edits, message):
    policy = _routed((1.0, 1.0, 1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match=message):
        policy.with_edits(edits)


def test_routes_need_a_learned_choice():
    with pytest.raises(ValueError, match="routes need a learned choice"):
        DenoisePolicy(route_sigmas=(0.2,), route_passes=(60,))
    # The rule alone drops them with the rest of the learned choice.
    policy = _routed((1.0, 1.0, 1.0, 0.0, 1.0)).with_presmooth_rule()
    assert policy.route_sigmas == () and not policy.learns_presmoothing


def test_the_learned_choice_takes_a_route_and_denoise_runs_it():
    from dmd_jax.checkpoints import load_pretrained

    clean, noisy, f = _noisy_box(0.1)
    policy = _routed((1.0, 1.0, 1.0, 0.0, 1.0))
    plan = presmooth_plan(policy, noisy, f, None)
    assert plan.route == 0 and plan.steps == 0
    assert presmooth_plan(_routed((1.0, 0.0, 1.0, 1.0, 1.0)), noisy, f, None).route is None
    bundle = load_pretrained()
    policy = bundle.policy.replace(**_route_fields((1.0, 1.0, 1.0, 0.0, 1.0)))
    out, info = denoise(noisy, f, bundle, policy=policy, return_info=True)
    assert info.path == "route" and info.route == "field σ0.2 ×60" and info.passes == 0
    np.testing.assert_allclose(out, routes.run_route(noisy, f, 0.2, 60), atol=1e-12)
    # A mesh that must go patch by patch gets the network.
    _, info = denoise(noisy, f, bundle, policy=policy, patch_size=300, return_info=True)
    assert info.path == "patches" and info.route is None
    # A caller's fixed count always runs the network.
    _, info = denoise(noisy, f, bundle, policy=policy, presmooth=0, return_info=True)
    assert info.path == "whole" and info.route is None and info.passes >= 1
    # The policy round-trips through JSON, as in a weights file.
    assert DenoisePolicy.from_dict(policy.to_dict()) == policy


def test_fit_learned_presmooth_picks_a_route_where_it_wins():
    from test_calibrate import _learn_rows

    rows = _learn_rows()
    # The route beats every count on the light half of the cases, loses on the rest.
    light = np.array([r[2] < 0.5 for r in rows])
    route_errors = np.where(light, 1.0, 50.0)[:, None]
    fit = cal.fit_learned_presmooth(rows, routes=[(0.2, 60)], route_errors=route_errors)
    assert fit.routes == ((0.2, 60),)
    features, _ = cal._split_rows(rows, cal.LEARN_GRID)
    options = fit.choose_options(features)
    n_grid = len(cal.LEARN_GRID)
    assert np.mean((options == n_grid) == light) > 0.9
    with pytest.raises(ValueError, match="choose_options"):
        fit.choose(features)
    policy = DenoisePolicy(presmooth_start=27.0, presmooth_per_step=4.5, **fit.policy_fields())
    assert policy.route_sigmas == (0.2,) and policy.route_passes == (60,)
    with pytest.raises(ValueError, match="route_errors must have shape"):
        cal.fit_learned_presmooth(rows, routes=[(0.2, 60)], route_errors=route_errors[:5])


def test_the_bundled_policy_carries_the_fitted_routes():
    from dmd_jax.checkpoints import load_pretrained

    policy = load_pretrained().policy
    routes_ = tuple(zip(policy.route_sigmas, policy.route_passes, strict=True))
    assert routes_ == cal.LEARN_ROUTES
    assert len(policy.presmooth_regrets) == (
        len(policy.presmooth_examples) // 11 * (len(policy.presmooth_grid) + len(routes_))
    )


def test_routes_are_host_side():
    """NumPy only: the routes import no JAX-side module of the package."""
    from test_package import import_graph

    assert import_graph()["dmd_jax.routes"] <= {
        "dmd_jax.constants",
        "dmd_jax.graph",
        "dmd_jax.mesh",
        "dmd_jax.topology",
    }

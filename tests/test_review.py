"""The review after the network (`dmd_jax.review`): its features, the policy fields that
carry it, its fit, and `denoise` keeping the network's result or taking a route."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation
from test_routes import _noisy_box, _route_fields

from dmd_jax import calibrate as cal
from dmd_jax import review, routes
from dmd_jax.inference import denoise
from dmd_jax.policy import DenoisePolicy
from dmd_jax.presmooth import FEATURE_NAMES

N_FEATURES = len(review.OUTPUT_FEATURE_NAMES)


def _review_fields(regrets_per_example, n_example=4, route=0):
    """A review over the network and the two routes of `_route_fields`; every example
    has the same regrets."""
    return {
        "review_route": route,
        "review_center": (0.0,) * N_FEATURES,
        "review_scale": (1.0,) * N_FEATURES,
        "review_examples": tuple(float(i % 5) for i in range(n_example * N_FEATURES)),
        "review_regrets": tuple(regrets_per_example) * n_example,
        "review_neighbours": 2,
    }


def _cascade_fields(regrets_per_example, n_example=4):
    """Two cascades (σ 0.2 ×4, σ 0.35 ×16) for `_review_fields`' examples; every
    example has the same regrets (the network's result, then each cascade)."""
    return {
        "cascade_sigmas": (0.2, 0.35),
        "cascade_passes": (4, 16),
        "cascade_regrets": tuple(regrets_per_example) * n_example,
        "cascade_neighbours": 2,
    }


def _reviewed(first_stage, review_regrets):
    return DenoisePolicy().with_edits(
        {**_route_fields(first_stage), **_review_fields(review_regrets)}
    )


# The first stage (counts 0, 1, 3, then two routes) always runs the network with no steps.
NETWORK_FIRST = (0.0, 1.0, 1.0, 1.0, 1.0)


def test_output_features_of_equal_outputs_and_of_a_flat():
    clean, noisy, f = _noisy_box(0.1)
    same = review.output_features(clean, clean, f)
    assert same.shape == (len(review.OUTPUT_FEATURE_NAMES),)
    # Equal results: no angle between them, and the same statistics twice.
    np.testing.assert_allclose(same[:2], np.log(0.5))
    np.testing.assert_allclose(same[2:5], same[5:8])
    # A subdivided box: flats everywhere but 90° creases, and no angle in between.
    assert same[2] > 0.85 and 0.0 < same[3] < 0.15
    noisy_vs_clean = review.output_features(noisy, clean, f)
    assert noisy_vs_clean[0] > np.log(2.0) and noisy_vs_clean[2] < same[2]


def test_output_features_are_scale_rotation_and_translation_free():
    _, noisy, f = _noisy_box(0.2)
    out = routes.run_route(noisy, f, 0.35, 10)
    want = review.review_features(noisy, out, f, 0.2, 60)
    rot = Rotation.from_euler("xyz", [0.3, -1.1, 2.0]).as_matrix()

    def move(x):
        return 1e-3 * x @ rot.T + [5.0, -2.0, 0.5]

    got = review.review_features(move(noisy), move(out), f, 0.2, 60)
    np.testing.assert_allclose(got, want, atol=1e-6)


def test_review_crop_is_a_connected_patch_in_any_face_order():
    from dmd_jax.presmooth import _edge_pairs

    small = trimesh.creation.icosphere(3)
    used, faces = review.review_crop(small.faces, len(small.vertices))
    assert used is None and np.array_equal(faces, small.faces)
    big = trimesh.creation.icosphere(6)  # 81,920 faces
    rng = np.random.default_rng(0)
    for order in (np.arange(len(big.faces)), rng.permutation(len(big.faces))):
        f = big.faces[order]
        used, faces = review.review_crop(f, len(big.vertices), max_faces=5_000)
        assert faces.shape == (5_000, 3) and faces.max() == used.size - 1
        # Every face is one of the mesh's, and the patch is one disc of ~1.5 pairs a face.
        assert {tuple(r) for r in np.sort(used[faces], axis=1)} <= {
            tuple(r) for r in np.sort(f, axis=1)
        }
        assert _edge_pairs(faces, used.size)[0].size > 1.45 * 5_000
        assert tuple(np.sort(f[0])) in {tuple(r) for r in np.sort(used[faces], axis=1)}


@pytest.mark.parametrize(
    "edits, message",
    [
        ({"review_route": 2}, "review_route must index one of the 2 routes"),
        ({"review_center": (0.0,) * 11}, f"review_center must hold {N_FEATURES} finite"),
        ({"review_route": -1}, "review_route must index one of the 2 routes"),
        ({"review_scale": (0.0,) * N_FEATURES}, "review_scale must be positive"),
        ({"review_examples": ()}, "review_examples must hold 1 to 20000 examples"),
        ({"review_regrets": (0.1,) * 8}, "review_regrets must hold 12 finite numbers"),
        ({"review_regrets": (float("inf"),) * 12}, "review_regrets: expected a finite"),
        ({"review_neighbours": 0}, "review_neighbours must be an integer >= 1"),
        ({"review_neighbours": 5}, "review_neighbours must be at most the 4 examples"),
    ],
)
def test_review_fields_are_checked_before_use(edits, message):
    policy = _reviewed(NETWORK_FIRST, (0.0, 1.0, 1.0))
    with pytest.raises(ValueError, match=message):
        policy.with_edits(edits)


def test_a_review_needs_the_learned_choice_and_its_routes():
    with pytest.raises(ValueError, match="a review needs the learned choice and its routes"):
        DenoisePolicy().with_edits(_review_fields((0.0, 1.0, 1.0)))
    with pytest.raises(ValueError, match="review_route needs a review"):
        DenoisePolicy(review_route=1)
    policy = _reviewed(NETWORK_FIRST, (0.0, 1.0, 1.0))
    assert policy.reviews and "review_examples 4 training examples" in policy.describe()
    assert not policy.without_review().reviews
    assert not policy.with_presmooth_rule().reviews  # no routes left to review against
    assert DenoisePolicy.from_dict(policy.to_dict()) == policy


def test_denoise_keeps_the_network_or_takes_the_route_the_review_picks():
    from dmd_jax.checkpoints import load_pretrained

    clean, noisy, f = _noisy_box(0.1)
    bundle = load_pretrained()
    base = bundle.policy.without_review().replace(**_route_fields(NETWORK_FIRST))
    plain, info = denoise(noisy, f, bundle, policy=base, return_info=True)
    assert info.path == "whole" and not info.reviewed
    keep = base.replace(**_review_fields((0.0, 1.0, 1.0)))
    out, info = denoise(noisy, f, bundle, policy=keep, return_info=True)
    assert info.path == "whole" and info.reviewed and info.route is None
    np.testing.assert_array_equal(out, plain)
    take = base.replace(**_review_fields((1.0, 1.0, 0.0)))
    out, info = denoise(noisy, f, bundle, policy=take, return_info=True)
    assert info.path == "route" and info.reviewed and info.route == "field σ0.35 ×20"
    assert info.passes >= 1  # the network ran before the review replaced its result
    np.testing.assert_allclose(out, routes.run_route(noisy, f, 0.35, 20), atol=1e-12)
    # A caller's fixed pre-smoothing runs the network alone, as does the patch path.
    _, info = denoise(noisy, f, bundle, policy=take, presmooth=0, return_info=True)
    assert info.path == "whole" and not info.reviewed
    _, info = denoise(noisy, f, bundle, policy=take, patch_size=300, return_info=True)
    assert info.path == "patches" and not info.reviewed


def test_denoise_runs_the_cascade_the_review_picks():
    from dmd_jax.checkpoints import load_pretrained

    clean, noisy, f = _noisy_box(0.1)
    bundle = load_pretrained()
    base = bundle.policy.without_review().replace(**_route_fields(NETWORK_FIRST))
    plain = denoise(noisy, f, bundle, policy=base)
    take = base.replace(**_review_fields((0.0, 1.0, 1.0)), **_cascade_fields((1.0, 1.0, 0.0)))
    out, info = denoise(noisy, f, bundle, policy=take, return_info=True)
    # The network ran, then the cascade on its result (not on the noisy mesh).
    assert info.path == "whole" and info.reviewed and info.route is None
    assert info.cascade == "cascade σ0.35 ×16" and info.passes >= 1
    np.testing.assert_allclose(out, routes.run_route(plain, f, 0.35, 16), atol=1e-9)
    keep = base.replace(**_review_fields((0.0, 1.0, 1.0)), **_cascade_fields((0.0, 1.0, 1.0)))
    out, info = denoise(noisy, f, bundle, policy=keep, return_info=True)
    assert info.cascade is None and info.route is None
    np.testing.assert_array_equal(out, plain)
    # A route the first choice takes is not followed by the second choice's cascade.
    route = base.replace(**_review_fields((1.0, 1.0, 0.0)), **_cascade_fields((1.0, 1.0, 0.0)))
    out, info = denoise(noisy, f, bundle, policy=route, return_info=True)
    assert info.route == "field σ0.35 ×20" and info.cascade is None


@pytest.mark.parametrize(
    "edits, message",
    [
        ({"cascade_sigmas": (0.2,)}, "cascade_sigmas and cascade_passes must pair up"),
        ({"cascade_sigmas": (0.2, 20.0)}, "cascade_sigmas must be range sigmas from 0.01"),
        ({"cascade_passes": (4, 0)}, "cascade_passes must be whole numbers from 1 to 500"),
        ({"cascade_passes": (4, 10**6)}, "cascade_passes must be whole numbers"),
        ({"cascade_regrets": (0.0, 1.0) * 4}, "cascade_regrets must hold 12 finite numbers"),
        ({"cascade_regrets": (float("nan"),) * 12}, "cascade_regrets: expected a finite"),
        ({"cascade_neighbours": 0}, "cascade_neighbours must be an integer >= 1"),
        ({"cascade_neighbours": 5}, "cascade_neighbours must be at most the 4 examples"),
    ],
)
def test_cascade_fields_are_checked_before_use(edits, message):
    policy = DenoisePolicy().with_edits(
        {
            **_route_fields(NETWORK_FIRST),
            **_review_fields((0.0, 1.0, 1.0)),
            **_cascade_fields((0.0, 1.0, 1.0)),
        }
    )
    assert policy.cascade_label(1) == "cascade σ0.35 ×16"
    assert not policy.without_review().cascade_sigmas
    with pytest.raises(ValueError, match=message):
        policy.with_edits(edits)
    with pytest.raises(ValueError, match="cascades need a review"):
        DenoisePolicy(cascade_sigmas=(0.2,), cascade_passes=(4,))


def _review_rows(n_mesh=10, seed=0):
    """Synthetic `review_rows`: every feature reads one hidden number (its own linear
    function of it, plus noise), whose sign says whether the route wins."""
    rng = np.random.default_rng(seed)
    slopes = np.linspace(-2.0, 3.0, N_FEATURES) + 0.1
    rows = []
    for m in range(n_mesh):
        for i in range(12):
            t = rng.uniform(-1.0, 1.0)
            x = slopes * t + rng.normal(scale=0.05, size=N_FEATURES)
            route_wins = t > 0
            errors = (5.0, 3.0, 6.0) if route_wins else (3.0, 5.0, 6.0)
            noise = rng.normal(size=len(FEATURE_NAMES))  # not read by the review
            rows.append([f"m{m}.ply", "gaussian", 0.1, i, *noise, *x, *errors])
    return rows


def test_fit_review_learns_when_a_route_wins():
    rows = _review_rows()
    fit = cal.fit_review(rows, 2, cascades=())
    assert fit.neighbours == min(fit.cv_regret, key=fit.cv_regret.get)
    test = _review_rows(n_mesh=3, seed=1)
    features, errors = cal.review_arrays(test, 3)
    chosen = fit.choose_options(features)
    assert np.mean(chosen == errors.argmin(axis=1)) > 0.85
    assert cal.regret_of(errors, chosen) < cal.regret_of(errors, np.zeros(len(test), int))
    policy = DenoisePolicy().with_edits({**_route_fields(NETWORK_FIRST), **fit.policy_fields()})
    assert policy.reviews and policy.review_neighbours == fit.neighbours
    with pytest.raises(ValueError, match="positive and finite"):
        cal.fit_review([[*r[:-3], 0.0, 1.0, 1.0] for r in rows], 2, cascades=())
    np.testing.assert_array_equal(cal.review_arrays(rows, 3)[0][0], rows[0][4 + 11 : -3])


def test_fit_review_offers_the_cascades_asked_for():
    # The same rows with two cascade columns: the first always best, the second worst.
    # The rows of the route test with two cascade columns: the first cascade beats the
    # network where the route does not win (and loses to the route where it does), the
    # second is always worst.
    rows = [[*r, 4.0 if r[-3] > r[-2] else 2.0, 9.0] for r in _review_rows()]
    cascades = ((0.2, 4), (0.35, 60))
    fit = cal.fit_review(rows, 2, cascades, offered=[(0.2, 4)])
    # The first choice is the route-only fit's; the second has its own regrets.
    first = cal.fit_review(rows, 2, cascades, offered=())
    assert fit.regrets == first.regrets and len(fit.regrets) == len(rows) * 3
    assert fit.cascades == ((0.2, 4),) and len(fit.cascade_regrets) == len(rows) * 2
    test = _review_rows(n_mesh=3, seed=1)
    features, errors = cal.review_arrays(test, 3)
    chosen, kept = fit.choose_options(features), first.choose_options(features)
    # Where the first choice keeps the network, the second runs the cascade (option 3:
    # after the network and two routes); where it takes a route, that route stays.
    assert np.all(chosen[kept == 0] == 3) and np.all(chosen[kept > 0] == kept[kept > 0])
    assert (kept == 0).sum() > 5
    fields = fit.policy_fields()
    assert fields["cascade_sigmas"] == (0.2,) and fields["cascade_passes"] == (4,)
    assert fields["cascade_neighbours"] == fit.cascade_neighbours
    assert first.policy_fields()["cascade_regrets"] == ()
    with pytest.raises(ValueError, match=r"cascades \[\(0.2, 16\)\] are not among"):
        cal.fit_review(rows, 2, cascades, offered=[(0.2, 16)])


def test_review_rows_measure_what_denoise_reviews(tmp_path):
    from dmd_jax.checkpoints import load_pretrained

    clean, _, f = _noisy_box(0.0)
    bundle = load_pretrained()
    bundle = bundle._replace(
        policy=bundle.policy.without_review().replace(
            **_route_fields(NETWORK_FIRST), **_review_fields((0, 1, 1))
        )
    )
    case = cal.Case("box.ply", clean, f)
    rows = cal.review_rows([case], bundle, [cal.LEARN_CONDITIONS[1]])
    assert len(rows) == 1 and len(rows[0]) == len(cal.review_header())
    _, level, seed, noisy = cal.learn_draw("box.ply", clean, f, cal.LEARN_CONDITIONS[1])
    assert rows[0][2:4] == [level, seed]
    out, info = denoise(
        noisy, f, bundle._replace(policy=bundle.policy.without_review()), return_info=True
    )
    from dmd_jax.presmooth import noise_features

    want = [*noise_features(noisy, f), *review.review_features(noisy, out, f, 0.2, 60)]
    n_error = 1 + 2 + len(cal.REVIEW_CASCADES)
    np.testing.assert_allclose(rows[0][4:-n_error], want, atol=1e-9)
    # The cascades' errors: their field and vertex update on the network's result.
    for i, (s, p) in enumerate(cal.REVIEW_CASCADES):
        want = cal._normal_error(routes.run_route(out, f, s, p), clean, f)
        assert rows[0][-len(cal.REVIEW_CASCADES) + i] == pytest.approx(want, abs=1e-9)
    from benchmarks.common import write_csv

    path = write_csv(tmp_path / "r.csv", cal.review_header(), rows)
    np.testing.assert_allclose(cal.read_review_csv(path)[0][2:], rows[0][2:], rtol=1e-6)


def test_review_is_host_side():
    """NumPy only: the review imports no JAX-side module of the package."""
    from test_package import import_graph

    assert import_graph()["dmd_jax.review"] <= {
        "dmd_jax.constants",
        "dmd_jax.graph",
        "dmd_jax.mesh",
        "dmd_jax.presmooth",
        "dmd_jax.routes",
        "dmd_jax.topology",
    }


def test_the_bundled_policy_carries_a_fitted_review():
    from dmd_jax.checkpoints import load_pretrained

    policy = load_pretrained().policy
    assert policy.reviews and policy.review_route == cal.REVIEW_ROUTE
    n_example = len(policy.review_examples) // N_FEATURES
    assert len(policy.review_regrets) == n_example * (1 + len(policy.route_sigmas))
    # The second choice offers the measured cascades.
    assert policy.cascade_sigmas and len(policy.cascade_sigmas) == len(cal.REVIEW_CASCADES)
    assert len(policy.cascade_regrets) == n_example * (1 + len(policy.cascade_sigmas))
    # Its examples are the training rows the review was fitted on, and their regrets.
    rows = cal.read_review_csv(_results_dir() / "review_learn_train.csv")
    assert n_example == len(rows)
    _, errors = cal.review_arrays(rows, 1 + len(policy.route_sigmas) + len(cal.REVIEW_CASCADES))
    second = errors[:, [0, *range(1 + len(policy.route_sigmas), errors.shape[1])]]
    want = np.log(second / second.min(axis=1, keepdims=True)).ravel()
    np.testing.assert_allclose(policy.cascade_regrets, want, atol=1e-4)


def _results_dir():
    from pathlib import Path

    return Path(__file__).resolve().parents[1] / "benchmarks" / "results"


def test_the_cli_says_when_the_review_ran_a_cascade(tmp_path, capsys):
    from dmd_jax.checkpoints import load_pretrained, save_weights
    from dmd_jax.cli import main
    from dmd_jax.io import save_mesh

    _, noisy, f = _noisy_box(0.1)
    bundle = load_pretrained()
    policy = (
        bundle.policy.without_review()
        .replace(**_route_fields(NETWORK_FIRST))
        .replace(**_review_fields((0.0, 1.0, 1.0)), **_cascade_fields((1.0, 0.0, 1.0)))
    )
    weights = save_weights(tmp_path / "w.msgpack", bundle.params, bundle.config, policy=policy)
    save_mesh(tmp_path / "noisy.obj", noisy, f)
    out = tmp_path / "out.obj"
    main(["denoise", str(tmp_path / "noisy.obj"), "-o", str(out), "--weights", str(weights)])
    said = capsys.readouterr().out
    assert "(its review ran cascade σ0.2 ×4 on the network's result)" in said

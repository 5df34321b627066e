"""The whole-mesh path's shape ladder (`dmd_jax.shape_ladder`) and the warm-up that
compiles its programs in advance (`dmd_jax.warmup`, `dmd-jax warmup`).

What must hold: every mesh pads to a rung that holds it, with little waste; a rung's
abstract inputs are exactly what `denoise` passes (else a warm-up compiles programs no
call loads); a warmed cache serves a mesh of another size without a compile.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_model_ell import bipyramid

from dmd_jax import compile_cache, shape_ladder
from dmd_jax.graph import build_mesh_graph, pad_mesh_graph


def grid(n: int):
    """An n x n vertex grid, two triangles a cell: interior valence 6."""
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    f = np.concatenate([np.stack([a, b, d], -1), np.stack([a, d, c], -1)]).reshape(-1, 3)
    x, y = np.meshgrid(np.arange(n), np.arange(n))
    v = np.stack([x.ravel(), y.ravel(), 0.1 * np.sin(x.ravel())], 1).astype(np.float64)
    return v, f


def test_rungs_grow_by_at_most_an_eighth_above_the_fine_start():
    r = shape_ladder.rungs_between(1_000, 4_000_000)
    assert r == sorted(set(r)) and r[0] == shape_ladder.SMALLEST_RUNG
    for a, b in zip(r[:-1], r[1:], strict=True):
        step = (b - a) / a
        if a >= shape_ladder.FINE_FROM:
            assert step <= 1 / shape_ladder.FINE_STEPS + 1e-9
        else:
            assert step <= 1 / shape_ladder.COARSE_STEPS + 1e-9
    # Every vertex count maps to the smallest rung at or above it.
    for n in (1, 1023, 1024, 1025, 8191, 8192, 8193, 51_000, 1_000_000):
        rung = shape_ladder.rung_above(n)
        assert rung >= n and not any(n <= x < rung for x in r)


def test_the_issue_range_takes_a_known_number_of_programs():
    # 10k-500k faces: 42 rungs of one program each (docs/cold-start.md quotes it).
    assert len(shape_ladder.rungs_between(10_000, 500_000)) == 42
    with pytest.raises(ValueError, match="min_faces"):
        shape_ladder.rungs_between(10, 5)


@pytest.mark.parametrize("n", [3, 40, 180])
def test_a_rung_holds_its_mesh_and_one_padding_vertex(n):
    v, f = grid(n)
    g = build_mesh_graph(f, len(v))
    sizes = shape_ladder.padded_sizes(g)
    assert sizes.n_vertex > g.n_vertex and sizes.n_face >= g.n_face
    assert sizes.n_vertex_edge >= g.vertex_senders.size
    assert sizes.n_face_edge >= g.face_senders.size
    pad_mesh_graph(g, sizes)  # holds it
    if g.n_vertex >= shape_ladder.FINE_FROM:
        assert sizes.n_vertex <= (g.n_vertex + 1) * (1 + 1 / shape_ladder.FINE_STEPS)
    # The estimate from counts alone (the memory plan's) is the same rung here.
    assert shape_ladder.rung_estimate(len(v), len(f)) <= sizes.n_vertex


def test_a_mesh_with_more_faces_than_the_multiples_takes_a_higher_rung():
    # Faces repeated (a non-manifold soup of copies): 4 faces per vertex.
    v, f = grid(30)
    f = np.concatenate([f, f[:, ::-1]])
    g = build_mesh_graph(f, len(v))
    sizes = shape_ladder.padded_sizes(g)
    assert sizes.n_face >= g.n_face and sizes.n_vertex >= g.n_face // 2
    with pytest.raises(ValueError, match="one mesh"):
        from dmd_jax.graph import batch_mesh_graphs

        shape_ladder.padded_sizes(batch_mesh_graphs([g, g]))


def _tables(v, f, aggregation):
    g = build_mesh_graph(f, len(v))
    return shape_ladder.with_tables(pad_mesh_graph(g, shape_ladder.padded_sizes(g)), aggregation)


def test_tables_take_the_standard_widths_or_none():
    v, f = grid(20)  # valence 6: a natural vertex table of 8 slots
    assert shape_ladder.layout_of(_tables(v, f, "auto")) == shape_ladder.STANDARD_WIDTHS
    assert shape_ladder.layout_of(_tables(v, f, "ell")) == shape_ladder.STANDARD_WIDTHS
    assert shape_ladder.layout_of(_tables(v, f, "segment_sum")) == (None, None)
    v, f = bipyramid(60)  # valence 60: no vertex table under auto, a wide one when forced
    assert shape_ladder.layout_of(_tables(v, f, "auto")) == (None, 4)
    assert shape_ladder.layout_of(_tables(v, f, "ell"))[0] >= 61
    assert (None, 4) in shape_ladder.LAYOUTS


def test_widened_tables_are_the_same_operator():
    from dmd_jax import ops

    v, f = grid(12)
    g = _tables(v, f, "auto")
    x = np.random.default_rng(0).standard_normal((g.n_vertex, 5)).astype(np.float32)
    dense = np.zeros((g.n_vertex, g.n_vertex))
    np.add.at(dense, (g.vertex_receivers, g.vertex_senders), g.vertex_edge_weight)
    got = np.asarray(ops.gcn_aggregate_ell(x, *g.vertex_ell))
    np.testing.assert_allclose(got, dense @ x, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("mesh", ["grid", "bipyramid"])
def test_abstract_inputs_are_what_denoise_passes(mesh):
    # The warm-up compiles for `abstract_graph`; `denoise` looks programs up by the
    # signature of its device arrays: they must agree, or no warmed program is ever used.
    import jax

    from dmd_jax.checkpoints import load_pretrained
    from dmd_jax.graph import pad_vertex_array
    from dmd_jax.inference import whole_mesh_graph

    v, f = grid(25) if mesh == "grid" else bipyramid(60)
    bundle = load_pretrained()
    g = whole_mesh_graph(f, len(v), "auto")
    x = jax.device_put(pad_vertex_array(v.astype(np.float32), g.n_vertex))
    real = (bundle.params, x, jax.tree.map(jax.device_put, g))
    abstract = (
        bundle.params,
        jax.ShapeDtypeStruct((g.n_vertex, 3), np.float32),
        shape_ladder.abstract_graph(g.n_vertex, shape_ladder.layout_of(g)),
    )
    assert compile_cache.signature(real) == compile_cache.signature(abstract)


def test_memory_plan_runs_a_mid_size_mesh_whole_without_measuring(monkeypatch):
    from dmd_jax import memory_plan
    from dmd_jax.config import preset

    def measure(config):
        raise AssertionError("measured (a compile) where the bound sufficed")

    monkeypatch.setattr(memory_plan, "network_bytes_per_vertex", measure)
    plan = memory_plan.plan(preset("small").model, 50_000, 100_000, max_memory="8GB")
    assert plan.whole
    with pytest.raises(AssertionError, match="measured"):
        memory_plan.plan(preset("small").model, 2_000_000, 4_000_000, max_memory="8GB")


@pytest.mark.slow
@pytest.mark.parametrize(
    "name, edits",
    [
        ("test", {}),
        ("small", {}),
        ("test", {"attention": True}),
        ("test", {"stn": True}),
        ("paper", {}),
    ],
)
def test_memory_bound_is_above_the_measurement(name, edits):
    from dmd_jax import memory_plan
    from dmd_jax.config import preset

    config = preset(name).model.replace(**edits)
    measured = memory_plan._measured_bytes_per_vertex(config)
    assert measured <= memory_plan.network_bytes_bound(config)


def test_warmup_cli_refuses_bad_ranges_and_a_disabled_cache(monkeypatch, capsys, tmp_path):
    from dmd_jax.cli import main

    monkeypatch.setenv(compile_cache.ENV, "0")
    assert main(["warmup", "--min-faces", "10"]) != 0
    assert "cache is off" in capsys.readouterr().err
    monkeypatch.setenv(compile_cache.ENV, str(tmp_path))
    monkeypatch.setenv(compile_cache.ENV_MAX_MB, "20")
    assert main(["warmup", "--max-faces", "100000"]) != 0
    assert compile_cache.ENV_MAX_MB in capsys.readouterr().err
    monkeypatch.delenv(compile_cache.ENV_MAX_MB)
    assert main(["warmup", "--min-faces", "5000", "--max-faces", "100"]) != 0
    assert "--min-faces" in capsys.readouterr().err
    assert main(["warmup", "--jobs", "0"]) != 0
    assert "--jobs" in capsys.readouterr().err


def test_denoise_notes_a_compile_once(capsys):
    import argparse

    from dmd_jax import forward
    from dmd_jax.cli import denoise as cli_denoise

    args = argparse.Namespace()
    before = cli_denoise._compiled_so_far("dmd")
    forward.COMPILED.append(("predict", 4.2))
    try:
        cli_denoise._note_compiles(args, before)
        cli_denoise._note_compiles(args, before)  # once per run
        assert cli_denoise._compiled_so_far("bnf") is None
    finally:
        forward.COMPILED.pop()
    err = capsys.readouterr().err
    assert err.count("note: compiled the network") == 1 and "dmd-jax warmup" in err
    assert "4.2 s" in err


@pytest.mark.slow
def test_a_warm_cache_serves_a_mesh_of_another_size_without_a_compile(tmp_path):
    # Two fresh processes: `dmd-jax warmup` over a small range, then `denoise` of two
    # meshes of different rungs in it: nothing compiled (the cache's miss events).
    import json
    import subprocess
    import sys

    env = {**__import__("os").environ, compile_cache.ENV: str(tmp_path / "cache")}
    warm = subprocess.run(
        [sys.executable, "-m", "dmd_jax.cli", "warmup", "--min-faces", "1500",
         "--max-faces", "2600", "--quiet"],
        env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert warm.returncode == 0, warm.stderr[-2000:]
    assert "compiled" in warm.stdout
    script = r"""
import json, sys
import numpy as np
from jax import monitoring
import threading
from dmd_jax import compile_cache, denoise
misses, hits = [], []
monitoring.register_event_listener(
    lambda e, **k: misses.append(e) if e == compile_cache.MISS_EVENT else None)
# Each program loaded by the preload `denoise` starts on its guess of the rung.
monitoring.register_event_listener(
    lambda e, **k: hits.append(threading.current_thread().name)
    if e == compile_cache.HIT_EVENT else None)
sys.path.insert(0, sys.argv[1])
from test_shape_ladder import grid
import jax
# The test modules import conftest, which turns float64 on (part of a program's key):
# off again, as in a user's process and in the warm-up.
jax.config.update("jax_enable_x64", False)
for n in (30, 36):   # 1,682 and 2,450 faces: rungs 1,024 and 1,536
    v, f = grid(n)
    v = v + 0.05 * np.random.default_rng(n).standard_normal(v.shape)
    denoise(v, f, iterations=1, presmooth=0)
print(json.dumps({"misses": len(misses), "hits": hits}))
"""
    run = subprocess.run(
        [sys.executable, "-c", script, str(__import__("pathlib").Path(__file__).parent)],
        env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr[-2000:]
    assert json.loads(run.stdout.strip().splitlines()[-1]) == {
        "misses": 0,
        "hits": ["dmd_jax-preload-predict"] * 2,
    }

"""`dmd_jax.parallel`: per-device groups, sharding, and 2-device training against 1 device.

The reference for multi-device training is `train.Trainer` on one device with the same
global batch (`pipeline.training_batch`): the parallel step must give the same params.
XLA's host-device count is fixed when JAX starts, so that comparison runs in a
subprocess with `XLA_FLAGS=--xla_force_host_platform_device_count=2`.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import numpy as np
import pytest
from conftest import icosphere, tetrahedron

from dmd_jax import geometry, parallel, pipeline

REPO = Path(__file__).resolve().parents[1]


def box():
    import trimesh

    b = trimesh.creation.box()
    return np.asarray(b.vertices, np.float64), np.asarray(b.faces, np.int32)


@pytest.fixture(scope="module")
def examples():
    return pipeline.make_examples([icosphere(1), tetrahedron(), box(), icosphere(2)])


def real_rows(batch: pipeline.Batch):
    """Noisy and clean rows of the real (unpadded) vertices of a padded batch."""
    m = np.asarray(batch.graph.vertex_mask)
    return np.asarray(batch.noisy)[m], np.asarray(batch.clean)[m]


# --------------------------------------------------------------------------------------
# Groups of a step
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(("batch_size", "n_group"), [(4, 2), (3, 2), (4, 3), (2, 1)])
def test_groups_are_the_training_batch_split(examples, batch_size, n_group):
    noise = pipeline.NoiseSettings()
    for step in (0, 1, 5):
        ref = pipeline.training_batch(examples, step, batch_size=batch_size, seed=3, noise=noise)
        groups = parallel.device_batches(
            examples, step, n_group=n_group, batch_size=batch_size, seed=3, noise=noise
        )
        assert sorted(groups) == list(range(n_group))
        # Common sizes: every leaf of every group has the same shape.
        shapes = {tuple(np.shape(x) for x in jax.tree.leaves(g)) for g in groups.values()}
        assert len(shapes) == 1
        # Slots are cut contiguously, so the groups in order are the reference batch.
        noisy = np.concatenate([real_rows(groups[i])[0] for i in range(n_group)])
        clean = np.concatenate([real_rows(groups[i])[1] for i in range(n_group)])
        ref_noisy, ref_clean = real_rows(ref)
        np.testing.assert_array_equal(noisy, ref_noisy)
        np.testing.assert_array_equal(clean, ref_clean)
        sizes = [len(groups[i].graph.n_vertex_per_graph) - 1 for i in range(n_group)]
        assert (
            max(sizes) - min(sizes) <= 1
            and sum(int(np.sum(groups[i].graph.n_vertex_per_graph > 0)) for i in range(n_group))
            == batch_size
        )


def test_only_the_requested_groups_are_built(examples):
    noise = pipeline.NoiseSettings()
    kwargs = dict(n_group=3, batch_size=4, seed=0, noise=noise)
    every = parallel.device_batches(examples, 2, **kwargs)
    one = parallel.device_batches(examples, 2, groups=[1], **kwargs)
    assert list(one) == [1]
    for a, b in zip(jax.tree.leaves(one[1]), jax.tree.leaves(every[1]), strict=True):
        np.testing.assert_array_equal(a, b)


def test_collate_to_equals_collate_at_its_own_sizes(examples):
    rng = np.random.default_rng(0)
    graphs = [examples[0].graph, examples[2].graph]
    noisy = [rng.standard_normal((g.n_vertex, 3)) for g in graphs]
    clean = [rng.standard_normal((g.n_vertex, 3)) for g in graphs]
    ref = pipeline.collate(noisy, clean, graphs)
    sizes = parallel.common_sizes([graphs])
    got = parallel.collate_to(noisy, clean, graphs, sizes)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(ref), strict=True):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


def test_common_sizes_hold_every_group(examples):
    g = [ex.graph for ex in examples]
    groups = [[g[0], g[3]], [g[1]], [g[2], g[1]]]
    sizes = parallel.common_sizes(groups)
    assert sizes.n_graph == 3  # at most two meshes per group, plus the padding graph
    for group in groups:
        noisy = [np.zeros((x.n_vertex, 3)) for x in group]
        batch = parallel.collate_to(noisy, noisy, group, sizes)
        assert batch.graph.n_vertex == sizes.n_vertex and batch.noisy.shape[0] == sizes.n_vertex
    with pytest.raises(ValueError, match="at least one mesh"):
        parallel.common_sizes([[g[0]], []])


def test_split_slots():
    parts = parallel.split_slots(5, 2)
    assert [p.tolist() for p in parts] == [[0, 1, 2], [3, 4]]
    assert [p.tolist() for p in parallel.split_slots(4, 4)] == [[0], [1], [2], [3]]
    with pytest.raises(ValueError, match="cannot feed 3 devices"):
        parallel.split_slots(2, 3)


# --------------------------------------------------------------------------------------
# Loss weights of the groups
# --------------------------------------------------------------------------------------


def test_term_counts_against_numpy(examples):
    noise = pipeline.NoiseSettings()
    groups = parallel.device_batches(examples, 0, n_group=2, batch_size=4, seed=1, noise=noise)
    for batch in groups.values():
        g = batch.graph
        clean = np.asarray(batch.clean, np.float64)
        counts = jax.tree.map(int, parallel.term_counts(batch.clean, g))
        n_real = int(g.n_vertex_per_graph.sum())
        assert counts["vertex"] == counts["curvature"] == counts["feature"] == n_real
        area = np.asarray(geometry.face_areas(clean, g.faces))
        assert counts["normal"] == int(np.sum(g.face_mask & (area > 0)))
        assert counts["chamfer"] == len(g.n_vertex_per_graph) - 1


# --------------------------------------------------------------------------------------
# Placement
# --------------------------------------------------------------------------------------


def test_shard_batch_on_one_device(examples):
    mesh = parallel.batch_mesh(jax.devices()[:1])
    assert parallel.local_groups(mesh) == [0]
    noise = pipeline.NoiseSettings()
    groups = parallel.device_batches(examples, 0, n_group=1, batch_size=2, seed=0, noise=noise)
    stacked = parallel.shard_batch(mesh, groups)
    assert stacked.noisy.shape == (1,) + groups[0].noisy.shape
    assert stacked.noisy.sharding.spec == jax.sharding.PartitionSpec(parallel.BATCH_AXIS)
    np.testing.assert_array_equal(np.asarray(stacked.graph.faces[0]), groups[0].graph.faces)
    with pytest.raises(ValueError, match="groups of this process"):
        parallel.shard_batch(mesh, {1: groups[0]})
    with pytest.raises(ValueError, match="one-axis mesh"):
        parallel.local_groups(jax.sharding.Mesh(np.asarray(jax.devices()[:1]), ("data",)))


def test_replicate_copies_values(examples):
    mesh = parallel.batch_mesh(jax.devices()[:1])
    tree = {"a": np.arange(6.0).reshape(2, 3), "b": np.int32(3)}
    out = parallel.replicate(mesh, tree)
    assert out["a"].sharding.is_fully_replicated
    np.testing.assert_array_equal(np.asarray(out["a"]), tree["a"])
    assert int(out["b"]) == 3


# --------------------------------------------------------------------------------------
# 2 devices against 1
# --------------------------------------------------------------------------------------

# Meshes and batch chosen so every step fits one vertex bucket on both sides (one
# compilation each, the same padded sizes): icosphere(1) 42 vertices, tetrahedron 4,
# box 8; a global batch of 3 is split 2 + 1, so the groups differ in size and the
# count weighting matters.
TWO_DEVICE_SCRIPT = textwrap.dedent(
    """
    import json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    sys.path.insert(0, {tests!r})
    from conftest import icosphere, tetrahedron
    from test_parallel import box
    from dmd_jax import config, parallel, pipeline, train

    assert jax.device_count() == 2, jax.devices()
    cfg = config.preset("test").with_edits(json.loads({edits!r}))
    examples = pipeline.make_examples([icosphere(1), tetrahedron(), box()])
    noise = pipeline.NoiseSettings()
    t = cfg.train
    steps = 3

    single = train.Trainer(cfg)
    batches = [
        pipeline.training_batch(
            examples, s, batch_size=t.batch_size, seed=t.seed, noise=noise, rotate=t.rotate
        )
        for s in range(steps)
    ]
    state = single.init(batches[0])
    ref_loss = []
    for b in batches:
        state, out = single.train_step(state, b)
        ref_loss.append(float(out["loss"]))

    mesh = parallel.batch_mesh()
    multi = parallel.ParallelTrainer(cfg, mesh)
    pstate, loss, shard_shapes, group_vertices = None, [], [], []
    for s in range(steps):
        groups = parallel.device_batches(
            examples, s, n_group=2, batch_size=t.batch_size, seed=t.seed, noise=noise,
            rotate=t.rotate,
        )
        group_vertices.append([int(g.graph.vertex_mask.sum()) for g in groups.values()])
        if pstate is None:
            pstate = multi.init(groups[0])
        batch = parallel.shard_batch(mesh, groups)
        shard_shapes.append([list(x.data.shape) for x in batch.noisy.addressable_shards])
        pstate, out = multi.train_step(pstate, batch)
        loss.append(float(out["loss"]))

    compiles = [single.compiles, multi.compiles]
    diff = jax.tree.map(
        lambda a, b: float(np.max(np.abs(np.asarray(a) - np.asarray(b)))),
        state.params, pstate.params,
    )
    scale = max(float(np.max(np.abs(np.asarray(a)))) for a in jax.tree.leaves(state.params))
    print(json.dumps({{
        "ref_loss": ref_loss, "loss": loss,
        "max_param_diff": max(jax.tree.leaves(diff)), "param_scale": scale,
        "step": [int(state.step), int(pstate.step)],
        "compiles": compiles,
        "param_replicated": all(
            x.sharding.is_fully_replicated for x in jax.tree.leaves(pstate.params)
        ),
        "shard_shapes": shard_shapes, "group_vertices": group_vertices,
    }}))
    """
)


# Compiling the loss dominates the run (about 20 s of CPU for the smallest model), so
# the default run trains a one-stream denoiser without the feature term; the slow one
# trains the whole test preset (FGT-8, every loss term).
CONFIGS = [
    pytest.param(
        {
            "model": {"dtype": "float64", "variant": "do_1s", "depth": 1, "n_agg": 1},
            "loss": {"feature": 0.0},
            "train": {"batch_size": 3},
        },
        id="denoiser-only",
    ),
    pytest.param(
        {"model": {"dtype": "float64"}, "train": {"batch_size": 3}},
        id="test-preset",
        marks=pytest.mark.slow,
    ),
]


@pytest.mark.parametrize("edits", CONFIGS)
def test_two_devices_equal_one_device(tmp_path, edits):
    env = dict(os.environ)
    # The optimised HLO of the train steps is dumped to check for the all-reduce.
    flags = "--xla_force_host_platform_device_count=2 --xla_dump_hlo_as_text "
    flags += f"--xla_dump_to={tmp_path} --xla_dump_hlo_module_re=.*step_fn.*"
    env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " " + flags).strip()
    env["JAX_PLATFORMS"] = "cpu"
    script = TWO_DEVICE_SCRIPT.format(tests=str(REPO / "tests"), edits=json.dumps(edits))
    proc = subprocess.run(
        [sys.executable, "-c", script],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["step"] == [3, 3]
    # One bucket on each side: one compiled step each.
    assert result["compiles"] == [1, 1]
    assert result["param_replicated"]
    # Each device holds its own group of the stacked batch, and the groups differ in
    # size (2 meshes and 1), so a plain mean over devices would not match.
    assert all(shapes == [[1, 64, 3], [1, 64, 3]] for shapes in result["shard_shapes"])
    assert all(len(set(v)) == 2 for v in result["group_vertices"])
    # The SPMD partitioner split the step over the two devices and summed across them.
    dumps = sorted(tmp_path.glob("*step_fn*after_optimizations.txt"))
    assert len(dumps) == 2, [p.name for p in tmp_path.iterdir()]
    partitioned = [p.read_text() for p in dumps if "num_partitions=2" in p.read_text()]
    assert len(partitioned) == 1 and "all-reduce(" in partitioned[0]
    # float64 model, same padded sizes on both sides: only the order of the sums
    # differs (measured: 1e-16 of the params after 3 steps). With different buckets the
    # float32 batch makes the targets' curvatures round differently, about 1e-7.
    np.testing.assert_allclose(result["loss"], result["ref_loss"], rtol=1e-9)
    assert result["max_param_diff"] <= 1e-9 * max(result["param_scale"], 1.0)


# Two JAX processes on this machine, one CPU device each, joined by
# `jax.distributed.initialize` and gloo collectives: the multi-host path (each process
# builds and places only its own group). Process 0 also trains on its own device alone.
MULTI_PROCESS_SCRIPT = textwrap.dedent(
    """
    import json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    pid, port = int(sys.argv[1]), sys.argv[2]
    jax.distributed.initialize(
        coordinator_address=f"localhost:{{port}}", num_processes=2, process_id=pid
    )
    import numpy as np
    sys.path.insert(0, {tests!r})
    from conftest import icosphere, tetrahedron
    from test_parallel import box
    from dmd_jax import config, parallel, pipeline, train

    assert jax.device_count() == 2 and jax.local_device_count() == 1
    cfg = config.preset("test").with_edits(json.loads({edits!r}))
    examples = pipeline.make_examples([icosphere(1), tetrahedron(), box()])
    noise = pipeline.NoiseSettings()
    t = cfg.train
    mesh = parallel.batch_mesh()
    mine = parallel.local_groups(mesh)
    multi = parallel.ParallelTrainer(cfg, mesh)
    state, loss = None, []
    for s in range(3):
        groups = parallel.device_batches(
            examples, s, n_group=mesh.size, batch_size=t.batch_size, seed=t.seed,
            noise=noise, rotate=t.rotate, groups=mine,
        )
        state = state or multi.init(groups[mine[0]])
        state, out = multi.train_step(state, parallel.shard_batch(mesh, groups))
        loss.append(float(out["loss"]))
    result = {{"pid": pid, "mine": mine, "loss": loss}}
    if pid == 0:
        single = train.Trainer(cfg)
        ref_state, ref = None, []
        for s in range(3):
            b = pipeline.training_batch(
                examples, s, batch_size=t.batch_size, seed=t.seed, noise=noise,
                rotate=t.rotate,
            )
            ref_state = ref_state or single.init(b)
            ref_state, out = single.train_step(ref_state, b)
            ref.append(float(out["loss"]))
        local = jax.tree.map(lambda a: np.asarray(a.addressable_data(0)), state.params)
        diff = jax.tree.map(
            lambda a, b: float(np.max(np.abs(a - np.asarray(b)))), local, ref_state.params
        )
        result["ref_loss"] = ref
        result["max_param_diff"] = max(jax.tree.leaves(diff))
    print(json.dumps(result))
    jax.distributed.shutdown()
    """
)


@pytest.mark.slow
def test_two_processes_equal_one_device():
    import socket

    with socket.socket() as s:
        s.bind(("localhost", 0))
        port = s.getsockname()[1]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)
    script = MULTI_PROCESS_SCRIPT.format(
        tests=str(REPO / "tests"), edits=json.dumps(CONFIGS[0].values[0])
    )
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", script, str(pid), str(port)],
            cwd=REPO,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for pid in (0, 1)
    ]
    results = []
    try:
        for proc in procs:
            out, err = proc.communicate(timeout=900)
            assert proc.returncode == 0, err[-4000:]
            results.append(json.loads(out.strip().splitlines()[-1]))
    finally:
        for proc in procs:  # a process left waiting for its peer
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    assert [r["mine"] for r in results] == [[0], [1]]
    assert results[0]["loss"] == results[1]["loss"]
    np.testing.assert_allclose(results[0]["loss"], results[0]["ref_loss"], rtol=1e-9)
    assert results[0]["max_param_diff"] <= 1e-9

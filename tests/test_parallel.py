"""One engine on one device and on several: per-device groups, placement, 2 devices vs 1.

The reference for multi-device training is `train.Trainer` on one device (a one-device
mesh, the batch one group) with the same global batch: the same `train.make_train_step`
on a two-device mesh, the batch in two groups, must give the same params. XLA's
host-device count is fixed when JAX starts, so that comparison runs in a subprocess with
`XLA_FLAGS=--xla_force_host_platform_device_count=2`.
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

from dmd_jax import parallel, pipeline
from dmd_jax.config import NoiseConfig

REPO = Path(__file__).resolve().parents[1]


def box():
    import trimesh

    b = trimesh.creation.box()
    return np.asarray(b.vertices, np.float64), np.asarray(b.faces, np.int32)


@pytest.fixture(scope="module")
def examples():
    return pipeline.make_examples([icosphere(1), tetrahedron(), box(), icosphere(2)])


def real_rows(batch: pipeline.Batch):
    """Noisy and clean rows of the real (unpadded) vertices of a padded batch, group by
    group."""
    m = np.asarray(batch.graph.vertex_mask)
    return np.asarray(batch.noisy)[m], np.asarray(batch.clean)[m]


def group(batch: pipeline.Batch, i: int) -> pipeline.Batch:
    return jax.tree.map(lambda x: x[i], batch)


# --------------------------------------------------------------------------------------
# Groups of a step
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(("batch_size", "n_group"), [(4, 2), (3, 2), (4, 3), (2, 1)])
def test_groups_are_the_training_batch_split(examples, batch_size, n_group):
    kwargs = dict(batch_size=batch_size, seed=3, noise=NoiseConfig())
    for step in (0, 1, 5):
        ref = pipeline.training_batch(examples, step, **kwargs)
        groups = pipeline.training_batch(examples, step, n_group=n_group, **kwargs)
        # Groups stacked on a leading axis: common padded sizes.
        assert ref.noisy.shape[0] == 1 and groups.noisy.shape[0] == n_group
        assert {np.shape(x)[0] for x in jax.tree.leaves(groups)} == {n_group}
        # Slots are cut contiguously, so the groups in order are the one-group batch.
        noisy, clean = real_rows(groups)
        ref_noisy, ref_clean = real_rows(ref)
        np.testing.assert_array_equal(noisy, ref_noisy)
        np.testing.assert_array_equal(clean, ref_clean)
        meshes = [
            int(np.sum(group(groups, i).graph.n_vertex_per_graph > 0)) for i in range(n_group)
        ]
        assert max(meshes) - min(meshes) <= 1 and sum(meshes) == batch_size


def test_only_the_requested_groups_are_built(examples):
    kwargs = dict(n_group=3, batch_size=4, seed=0, noise=NoiseConfig())
    every = pipeline.training_batch(examples, 2, **kwargs)
    one = pipeline.training_batch(examples, 2, groups=[1], **kwargs)
    assert one.noisy.shape[0] == 1
    for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(group(every, 1)), strict=True):
        np.testing.assert_array_equal(a[0], b)


def test_collate_at_given_sizes_equals_collate_at_its_own(examples):
    rng = np.random.default_rng(0)
    graphs = [examples[0].graph, examples[2].graph]
    noisy = [rng.standard_normal((g.n_vertex, 3)) for g in graphs]
    clean = [rng.standard_normal((g.n_vertex, 3)) for g in graphs]
    ref = pipeline.collate(noisy, clean, graphs)
    got = pipeline.collate(noisy, clean, graphs, pipeline.common_sizes([graphs]))
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(ref), strict=True):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


def test_common_sizes_hold_every_group(examples):
    g = [ex.graph for ex in examples]
    groups = [[g[0], g[3]], [g[1]], [g[2], g[1]]]
    sizes = pipeline.common_sizes(groups)
    assert sizes.n_graph == 3  # at most two meshes per group, plus the padding graph
    for graphs in groups:
        noisy = [np.zeros((x.n_vertex, 3)) for x in graphs]
        batch = pipeline.collate(noisy, noisy, graphs, sizes)
        assert batch.graph.n_vertex == sizes.n_vertex and batch.noisy.shape[0] == sizes.n_vertex
    with pytest.raises(ValueError, match="at least one mesh"):
        pipeline.common_sizes([[g[0]], []])


def test_split_slots():
    parts = pipeline.split_slots(5, 2)
    assert [p.tolist() for p in parts] == [[0, 1, 2], [3, 4]]
    assert [p.tolist() for p in pipeline.split_slots(4, 4)] == [[0], [1], [2], [3]]
    with pytest.raises(ValueError, match="cannot feed 3 devices"):
        pipeline.split_slots(2, 3)


# --------------------------------------------------------------------------------------
# Placement
# --------------------------------------------------------------------------------------


def test_shard_batch_on_one_device(examples):
    mesh = parallel.batch_mesh(jax.devices()[:1])
    assert parallel.local_groups(mesh) == [0]
    batch = pipeline.training_batch(examples, 0, batch_size=2, seed=0, noise=NoiseConfig())
    placed = parallel.shard_batch(mesh, batch)
    assert placed.noisy.shape == batch.noisy.shape
    assert placed.noisy.sharding.spec == jax.sharding.PartitionSpec(parallel.BATCH_AXIS)
    np.testing.assert_array_equal(np.asarray(placed.graph.faces), batch.graph.faces)
    with pytest.raises(ValueError, match="groups of this process"):
        parallel.shard_batch(mesh, pipeline.stack([batch, batch]))
    with pytest.raises(ValueError, match="one-axis mesh"):
        parallel.local_groups(jax.sharding.Mesh(np.asarray(jax.devices()[:1]), ("data",)))


def test_sum_over_groups_on_one_device_is_the_shard_map_it_replaces():
    """One device: `group_fn` called directly, at index 0, with the whole blocks; the same
    values, and under `grad` and `vmap`, as the `shard_map` + `psum` it stands for (the
    several-device path is `test_two_devices_equal_one_device`)."""
    from jax.sharding import PartitionSpec as P

    mesh = parallel.batch_mesh(jax.devices()[:1])
    axis = parallel.BATCH_AXIS
    specs = (P(), P(axis))

    def group_fn(index, w, x):
        key = jax.random.fold_in(jax.random.PRNGKey(3), index)
        return {"s": (w * x[0]).sum() + jax.random.normal(key), "n": x.shape[0] * 1.0}

    def reference(w, x):
        def body(w, x):
            return jax.lax.psum(group_fn(jax.lax.axis_index(axis), w, x), axis)

        return jax.shard_map(body, mesh=mesh, in_specs=specs, out_specs=P())(w, x)

    f = parallel.sum_over_groups(group_fn, mesh, specs)
    w, x = np.linspace(-1, 1, 5), np.arange(10.0).reshape(1, 2, 5)

    def grad_s(fn):
        return jax.jit(jax.vmap(jax.grad(lambda w, x: fn(w, x)["s"]), in_axes=(0, None)))

    ws = np.stack([w, 2 * w])
    np.testing.assert_allclose(grad_s(f)(ws, x), grad_s(reference)(ws, x), rtol=1e-6)
    got, want = jax.jit(f)(w, x), jax.jit(reference)(w, x)
    for k in want:
        np.testing.assert_allclose(got[k], want[k], rtol=1e-6)
    with pytest.raises(ValueError, match="one-axis mesh"):
        parallel.sum_over_groups(
            group_fn, jax.sharding.Mesh(np.asarray(jax.devices()[:1]), ("d",)), specs
        )


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
    t = cfg.train
    kwargs = dict(batch_size=t.batch_size, seed=t.seed, noise=cfg.noise, rotate=t.rotate)
    steps = 3

    # The same Trainer, on a one-device mesh with the batch in one group ...
    single = train.Trainer(cfg)
    batches = [pipeline.training_batch(examples, s, **kwargs) for s in range(steps)]
    state = single.init(batches[0])
    ref_loss = []
    for b in batches:
        state, out = single.train_step(state, b)
        ref_loss.append(float(out["loss"]))

    # ... and on both devices with the batch in two groups.
    mesh = parallel.batch_mesh()
    multi = train.Trainer(cfg, mesh)
    pstate, loss, shard_shapes, group_vertices = None, [], [], []
    for s in range(steps):
        groups = pipeline.training_batch(examples, s, n_group=2, **kwargs)
        group_vertices.append([int(m.sum()) for m in groups.graph.vertex_mask])
        if pstate is None:
            pstate = multi.init(groups)
        placed = parallel.shard_batch(mesh, groups)
        shard_shapes.append([list(x.data.shape) for x in placed.noisy.addressable_shards])
        pstate, out = multi.train_step(pstate, groups)
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
        marks=pytest.mark.slow,  # ~30 s on 2 idle cores
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
    flags += f"--xla_dump_to={tmp_path} --xla_dump_hlo_module_re=.*jit_step.*"
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
    # One program per mesh; the two-device one sums the groups' terms across devices.
    dumps = sorted(tmp_path.glob("*jit_step*after_optimizations.txt"))
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
    t = cfg.train
    kwargs = dict(batch_size=t.batch_size, seed=t.seed, noise=cfg.noise, rotate=t.rotate)
    mesh = parallel.batch_mesh()
    mine = parallel.local_groups(mesh)
    multi = train.Trainer(cfg, mesh)
    state, loss = None, []
    for s in range(3):
        groups = pipeline.training_batch(
            examples, s, n_group=mesh.size, groups=mine, **kwargs
        )
        state = state or multi.init(groups)
        state, out = multi.train_step(state, groups)
        loss.append(float(out["loss"]))
    result = {{"pid": pid, "mine": mine, "loss": loss}}
    if pid == 0:
        single = train.Trainer(cfg, parallel.batch_mesh(jax.local_devices()))
        ref_state, ref = None, []
        for s in range(3):
            b = pipeline.training_batch(examples, s, **kwargs)
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


def run_two_processes(script: str, *args: str) -> list[dict]:
    """Runs `script` as processes 0 and 1 of a `jax.distributed` job on one machine.

    Each process gets `argv[1:] = [process id, coordinator port, *args]` and must print
    one JSON object as its last line; returns them in process order.
    """
    import socket

    with socket.socket() as s:
        s.bind(("localhost", 0))
        port = s.getsockname()[1]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", script, str(pid), str(port), *args],
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
    return results


@pytest.mark.slow
def test_two_processes_equal_one_device():
    script = MULTI_PROCESS_SCRIPT.format(
        tests=str(REPO / "tests"), edits=json.dumps(CONFIGS[0].values[0])
    )
    results = run_two_processes(script)
    assert [r["mine"] for r in results] == [[0], [1]]
    assert results[0]["loss"] == results[1]["loss"]
    np.testing.assert_allclose(results[0]["loss"], results[0]["ref_loss"], rtol=1e-9)
    assert results[0]["max_param_diff"] <= 1e-9


# --------------------------------------------------------------------------------------
# train.train(..., data_parallel=True) and the CLI flags
# --------------------------------------------------------------------------------------

# One subprocess with 2 CPU devices runs the training loop four times: on one device, and
# data-parallel uninterrupted, stopped after one step and resumed. A persistent
# compilation cache lets the later runs load the programs the first ones compiled.
TRAIN_LOOP_SCRIPT = textwrap.dedent(
    """
    import json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_compilation_cache_dir", sys.argv[2])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    import numpy as np
    from pathlib import Path
    sys.path.insert(0, {tests!r})
    from conftest import icosphere, tetrahedron
    from test_parallel import box
    from dmd_jax import config, pipeline, train

    assert jax.device_count() == 2, jax.devices()
    work = Path(sys.argv[1])
    cfg = config.preset("test").with_edits(json.loads({edits!r}))
    examples = pipeline.make_examples([icosphere(1), tetrahedron(), box()])
    evals = {{"test_intra": examples[1:]}}

    def run(name, **kwargs):
        out = train.train(
            cfg, examples, work / name, eval_sets=evals, progress=False, **kwargs
        )
        rows = [json.loads(x) for x in (work / name / "log.jsonl").read_text().splitlines()]
        return out, rows

    single, single_rows = run("single")
    multi, multi_rows = run("multi", data_parallel=True)
    stopped, _ = run("resumed", data_parallel=True, hooks=[train.StopAfter(1)])
    resumed, resumed_rows = run("resumed", data_parallel=True)

    def params(out):
        return jax.tree.leaves(jax.device_get(out["state"].params))

    def loss(rows):
        return [r["loss"] for r in rows if r["kind"] == "train"]

    def evaluation(out):
        return {{k: v for k, v in out.items() if k.startswith("test_intra/")}}

    diff = max(
        float(np.max(np.abs(a - b))) for a, b in zip(params(single), params(multi))
    )
    scale = max(float(np.max(np.abs(a))) for a in params(single))
    try:
        run("nan", data_parallel=True, hooks=[train.InjectNaN(1)])
        nan_error = None
    except train.NonFiniteLossError as exc:
        nan_error = str(exc)
    try:
        train.train(
            cfg.with_edits({{"train": {{"batch_size": 1}}}}), examples, work / "small",
            progress=False, data_parallel=True,
        )
        error = None
    except ValueError as exc:
        error = str(exc)
    print(json.dumps({{
        "step": [single["step"], multi["step"], stopped["step"], resumed["step"]],
        "compiles": [single["compiles"], multi["compiles"], resumed["compiles"]],
        "loss": [loss(single_rows), loss(multi_rows)],
        "eval": [evaluation(single), evaluation(multi)],
        "max_param_diff": diff, "param_scale": scale,
        "replicated": all(
            x.sharding.is_fully_replicated and len(x.sharding.device_set) == 2
            for x in jax.tree.leaves(resumed["state"])
        ),
        "resumed_equal": all(
            np.array_equal(a, b) for a, b in zip(params(multi), params(resumed))
        ),
        "resumed_loss": loss(resumed_rows),
        "best_saved": (work / "multi" / "checkpoints" / "best").is_dir(),
        "nan_error": nan_error,
        "small_error": error, "small_workdir": (work / "small").exists(),
    }}))
    """
)


@pytest.mark.slow  # measured 15-50 s on 2 idle cores; `make test-slow` runs it
def test_train_loop_data_parallel_on_two_devices(tmp_path):
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    flags = "--xla_force_host_platform_device_count=2"
    env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " " + flags).strip()
    edits = {**CONFIGS[0].values[0], "train": {"batch_size": 3, "steps": 3, "log_every": 1}}
    script = TRAIN_LOOP_SCRIPT.format(tests=str(REPO / "tests"), edits=json.dumps(edits))
    proc = subprocess.run(
        [sys.executable, "-c", script, str(tmp_path / "runs"), str(tmp_path / "cache")],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    # (a) The data-parallel loop equals the single-device loop: losses, params and the
    # final evaluation (of the merged params), to the order of float64 sums.
    assert result["step"] == [3, 3, 1, 3]
    assert result["compiles"] == [1, 1, 1]
    np.testing.assert_allclose(result["loss"][1], result["loss"][0], rtol=1e-9)
    assert result["max_param_diff"] <= 1e-9 * max(result["param_scale"], 1.0)
    single_eval, multi_eval = result["eval"]
    assert single_eval and single_eval.keys() == multi_eval.keys()
    for key, value in single_eval.items():
        np.testing.assert_allclose(multi_eval[key], value, rtol=1e-7, err_msg=key)
    assert result["best_saved"]
    # (b) Stopped after one step and resumed from its checkpoint (restored on the host,
    # then replicated): the same params, bit for bit, as the uninterrupted run.
    assert result["replicated"]
    assert result["resumed_equal"]
    assert result["resumed_loss"][1:] == result["loss"][1][1:]
    # A NaN batch (in every group) stops the data-parallel loop as it stops the other.
    assert "non-finite loss (nan) at step 1" in result["nan_error"]
    # (c) A global batch smaller than the device count: a clear error, no workdir.
    assert "at least one mesh per device" in result["small_error"]
    assert "train.batch_size is 1 but there are 2 devices" in result["small_error"]
    assert not result["small_workdir"]


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--coordinator", "localhost:1234"], "missing --num-processes, --process-id"),
        (["--num-processes", "2", "--process-id", "0"], "missing --coordinator"),
        (["--coordinator", "localhost", "--num-processes", "2", "--process-id", "0"], "HOST:PORT"),
        (["--coordinator", "h:1", "--num-processes", "2", "--process-id", "2"], "0..1"),
        (["--coordinator", "h:1", "--num-processes", "0", "--process-id", "0"], "at least 1"),
    ],
)
def test_cli_multi_host_flags_are_checked(tmp_path, monkeypatch, capsys, flags, message):
    from dmd_jax import cli

    def refuse(**kwargs):
        raise AssertionError(f"jax.distributed.initialize called with {kwargs}")

    monkeypatch.setattr(jax.distributed, "initialize", refuse)
    argv = ["train", "--data", str(tmp_path / "data"), "--workdir", str(tmp_path / "run")]
    assert cli.main(argv + ["--data-parallel"] + flags) == 2
    err = capsys.readouterr().err
    assert "dmd-jax train: error:" in err and message in err
    assert not (tmp_path / "run").exists()


def test_cli_multi_host_flags_initialize_first(tmp_path, monkeypatch, capsys):
    from dmd_jax import cli

    calls = []
    monkeypatch.setattr(jax.distributed, "initialize", lambda **kw: calls.append(kw))
    argv = ["train", "--data", str(tmp_path / "data"), "--workdir", str(tmp_path / "run")]
    flags = ["--coordinator", "10.0.0.1:1234", "--num-processes", "2", "--process-id", "0"]
    # Without --data-parallel the flags are refused before initializing anything.
    assert cli.main(argv + flags) == 2
    assert "need --data-parallel" in capsys.readouterr().err and not calls
    # With it, initialize comes first; the missing dataset is found only afterwards.
    assert cli.main(argv + flags + ["--data-parallel"]) == 2
    assert calls == [{"coordinator_address": "10.0.0.1:1234", "num_processes": 2, "process_id": 0}]
    assert "no such dataset directory" in capsys.readouterr().err


# Two JAX processes (one CPU device each) run the data-parallel loop in one shared
# workdir, stopped after one step and resumed: Orbax checkpoints from process 0, only
# process 0 writes the log. Process 0 then trains on its own device alone.
MULTI_PROCESS_TRAIN_SCRIPT = textwrap.dedent(
    """
    import json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    pid, port, work = int(sys.argv[1]), sys.argv[2], sys.argv[3]
    jax.distributed.initialize(
        coordinator_address=f"localhost:{{port}}", num_processes=2, process_id=pid
    )
    import numpy as np
    from pathlib import Path
    sys.path.insert(0, {tests!r})
    from conftest import icosphere, tetrahedron
    from test_parallel import box
    from dmd_jax import config, parallel, pipeline, train

    assert jax.device_count() == 2 and jax.local_device_count() == 1
    cfg = config.preset("test").with_edits(json.loads({edits!r}))
    examples = pipeline.make_examples([icosphere(1), tetrahedron(), box()])
    evals = {{"test_intra": examples[1:]}}
    run = Path(work) / "run"
    kwargs = dict(eval_sets=evals, progress=False, data_parallel=True)
    stopped = train.train(cfg, examples, run, hooks=[train.StopAfter(1)], **kwargs)
    final = train.train(cfg, examples, run, **kwargs)
    params = jax.tree.map(lambda a: np.asarray(a.addressable_data(0)), final["state"].params)
    result = {{"pid": pid, "step": [stopped["step"], final["step"]],
               "normal_deg": final.get("test_intra/normal_deg")}}
    if pid == 0:
        t = cfg.train
        single = train.Trainer(cfg, parallel.batch_mesh(jax.local_devices()))
        state, ref = None, []
        for s in range(t.steps):
            b = pipeline.training_batch(
                examples, s, batch_size=t.batch_size, seed=t.seed, noise=cfg.noise,
                rotate=t.rotate,
            )
            state = state or single.init(b)
            state, out = single.train_step(state, b)
            ref.append(float(out["loss"]))
        rows = [json.loads(x) for x in (run / "log.jsonl").read_text().splitlines()]
        result["log_steps"] = [r["step"] for r in rows if r["kind"] == "train"]
        result["loss"] = [r["loss"] for r in rows if r["kind"] == "train"]
        result["ref_loss"] = ref
        result["max_param_diff"] = max(
            float(np.max(np.abs(a - np.asarray(b))))
            for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(state.params))
        )
        result["checkpoints"] = sorted(
            p.name for p in (run / "checkpoints" / "latest").iterdir() if p.name.isdigit()
        )
    print(json.dumps(result))
    jax.distributed.shutdown()
    """
)


@pytest.mark.slow
def test_two_processes_train_loop_with_resume(tmp_path):
    edits = {**CONFIGS[0].values[0], "train": {"batch_size": 3, "steps": 3, "log_every": 1}}
    script = MULTI_PROCESS_TRAIN_SCRIPT.format(tests=str(REPO / "tests"), edits=json.dumps(edits))
    results = run_two_processes(script, str(tmp_path))
    assert [r["step"] for r in results] == [[1, 3], [1, 3]]
    assert results[0]["normal_deg"] == results[1]["normal_deg"] is not None
    first = results[0]
    assert first["log_steps"] == [1, 2, 3]  # one row per step: only process 0 logs
    assert first["checkpoints"] == ["1", "3"]
    np.testing.assert_allclose(first["loss"], first["ref_loss"], rtol=1e-9)
    assert first["max_param_diff"] <= 1e-9


@pytest.mark.slow
def test_train_loop_data_parallel_on_one_device(tmp_path, examples):
    from dmd_jax import config, train

    edits = {**CONFIGS[0].values[0], "train": {"batch_size": 2, "steps": 2}}
    cfg = config.preset("test").with_edits(edits)
    data = examples[:3]
    single = train.train(cfg, data, tmp_path / "single", progress=False)
    multi = train.train(cfg, data, tmp_path / "multi", progress=False, data_parallel=True)
    assert multi["step"] == 2 and multi["compiles"] == 1
    for a, b in zip(
        jax.tree.leaves(jax.device_get(single["state"].params)),
        jax.tree.leaves(jax.device_get(multi["state"].params)),
        strict=True,
    ):
        np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-12)

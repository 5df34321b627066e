"""The training engine's settings: every one changes what a step or a run does."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import icosphere, tetrahedron

from dmd_jax import config, pipeline, train

# A one-stream denoiser without the feature term: the cheapest model to compile.
TINY = {
    "model": {"variant": "do_1s", "depth": 1, "n_agg": 1},
    "loss": {"feature": 0.0},
    "train": {"batch_size": 2, "steps": 4, "eval_every": 0, "ckpt_every": 0},
}


def _update(cfg, grads, params):
    tx = train.make_optimizer(cfg)
    updates, _ = tx.update(grads, tx.init(params), params)
    return updates


def test_adam_eps_reaches_the_optimizer():
    params = {"w": jnp.zeros(3)}
    grads = {"w": jnp.array([1e-9, 1e-6, 1.0])}
    # A constant rate: the preset's cosine schedule starts its warm-up at 0.
    base = config.preset("test").with_edits({"train": {"schedule": "constant"}})
    default = _update(base, grads, params)["w"]
    large = _update(base.with_edits({"train": {"eps": 1.0}}), grads, params)["w"]
    # Adam's first step is -lr * g / (|g| + eps): eps = 1 shrinks the small gradients.
    assert np.all(np.abs(large) < np.abs(default))
    np.testing.assert_allclose(default[2], -base.train.lr, rtol=1e-6)


def test_phase_loss_switches_terms_off():
    cfg = config.preset("test").with_edits({"train": {"scheme": "alter"}})
    fe = train.phase_loss(cfg, "fe")
    assert (fe.vertex, fe.normal, fe.curvature, fe.chamfer, fe.feature) == (0, 0, 0, 0, 1)
    assert train.phase_loss(cfg, "rest") == cfg.loss.with_edits({"feature": 0.0})
    assert train.phase_loss(cfg, "all") == cfg.loss
    u_fe = cfg.with_edits({"train": {"scheme": "u_fe"}})
    assert train.phase_loss(u_fe, "all").feature == 0.0


@pytest.mark.parametrize(("log_every", "rows"), [(1, [1, 2, 3, 4]), (3, [3, 4]), (0, [4])])
def test_log_every_sets_the_logged_steps(tmp_path, log_every, rows):
    cfg = config.preset("test").with_edits(TINY).with_edits({"train": {"log_every": log_every}})
    examples = pipeline.make_examples([icosphere(1), tetrahedron()])
    out = train.train(cfg, examples, tmp_path, progress=False)
    assert out["step"] == 4
    logged = [json.loads(x) for x in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in logged if r["kind"] == "train"] == rows


def test_one_device_is_a_one_device_mesh():
    cfg = config.preset("test").with_edits(TINY)
    trainer = train.Trainer(cfg)
    assert trainer.mesh.size == 1 and trainer.mesh.devices.flat[0] == jax.devices()[0]
    examples = pipeline.make_examples([icosphere(1), tetrahedron()])
    kw = dict(batch_size=2, seed=0, noise=cfg.noise)
    state = trainer.init(pipeline.training_batch(examples, 0, **kw))
    state, out = trainer.train_step(state, pipeline.training_batch(examples, 0, **kw))
    assert int(state.step) == 1 and trainer.compiles == 1
    # The terms of the preset's recipe (curvature and chamfer weigh 0 there, so they
    # are not computed) and the normal-first head's own face-normal term.
    assert set(out) == {"loss", "grad_norm", "vertex", "normal", "face_normal"}


# ---------------------------------------------------------------- train_and_evaluate


@pytest.fixture(scope="module")
def run_data(tmp_path_factory):
    """A small procedural dataset and a real-mesh folder with train and val files."""
    from dmd_jax.data import make_dataset, real
    from dmd_jax.io import save_mesh

    root = tmp_path_factory.mktemp("run_data")
    dataset = make_dataset(
        root / "ds",
        per_category=3,
        categories=("blob", "torus"),
        test_inter=("torus",),
        min_vertices=150,
        max_vertices=300,
        workers=1,
        progress=False,
    )
    folder = root / "real"
    folder.mkdir()
    names = [f"part{i}.ply" for i in range(40)]
    train_name = next(n for n in names if not real.is_validation(n))
    val_name = next(n for n in names if real.is_validation(n))
    # 1,280 faces: cut into patches under the small patch sizes of `REAL`.
    save_mesh(folder / train_name, *icosphere(3))
    save_mesh(folder / val_name, *icosphere(2))
    return dataset.root, folder


# Real-mesh settings away from their defaults, so a field that did not reach the loaders
# would show; the patch sizes stay above `real.mesh_patches`' 200-face minimum.
REAL = {
    "real_patch_faces": 300,
    "real_faces_per_patch": 500,
    "real_patches_per_mesh": 2,
    "real_val_patch_faces": 250,
    "real_val_patches_per_mesh": 1,
}


def _run_config(run_data, **data):
    ds, _ = run_data
    edits = {"data": {"dataset_dir": str(ds), **data}}
    edits["train"] = {"steps": 3, "batch_size": 1, "log_every": 1}
    return config.preset("test").with_edits(TINY).with_edits(edits)


def _log(workdir):
    """The rows of a run's log, wall times left out."""
    rows = [json.loads(x) for x in (workdir / "log.jsonl").read_text().splitlines()]
    return [{k: v for k, v in r.items() if k != "time"} for r in rows]


def _leaves(result):
    return jax.tree.leaves(jax.device_get(result["state"].params))


# Slow (42 s on 2 cores): a one-time check of the refactor against the old assembly;
# the CLI and train_and_evaluate tests of the default suite run the path itself.
@pytest.mark.slow
def test_train_and_evaluate_is_the_old_cli_assembly(tmp_path, run_data):
    """The refactored path trains exactly what `dmd-jax train` assembled by hand before
    `train_and_evaluate` existed (its code written out here, 2026-12-02): the same
    meshes, evaluation sets, benchmark evaluation noise and padding; equal losses,
    evaluation and params, bit for bit."""
    from dmd_jax.data import load_dataset, real
    from dmd_jax.data.training_sets import TEST_SPLITS
    from dmd_jax.pipeline import make_examples
    from dmd_jax.protocol import benchmark_noise_config

    ds, folder = run_data
    cfg = _run_config(run_data, real_root=str(folder), eval_meshes_per_split=2, **REAL)
    new = train.train_and_evaluate(cfg, tmp_path / "new", progress=False)

    data = load_dataset(ds)
    train_ex = make_examples(data.arrays("train"))
    evals = {s: make_examples([r.load() for r in data.split(s)[:2]]) for s in TEST_SPLITS}
    seed = cfg.train.seed
    train_ex += make_examples(
        real.load_real_patches(
            folder, "train", max_faces=300, faces_per_patch=500, max_patches=2, seed=seed
        )
    )
    evals["val"] = make_examples(
        real.load_real_patches(folder, "val", max_faces=250, max_patches=1, seed=seed)
    )
    old = train.train(
        cfg,
        train_ex,
        tmp_path / "old",
        eval_sets=evals,
        progress=False,
        eval_noise=benchmark_noise_config(),
        pad_to="largest",
    )
    assert new["step"] == old["step"] == 3
    # Two patches of the real training mesh joined the dataset's training meshes.
    assert len(train_ex) == len(data.split("train")) + 2
    assert _log(tmp_path / "new") == _log(tmp_path / "old")
    scores = {k: v for k, v in old.items() if "/" in k}
    assert {k: new[k] for k in scores} == scores and "val/normal_deg" in scores
    for a, b in zip(_leaves(new), _leaves(old), strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.slow  # measured 15-50 s on 2 idle cores; `make test-slow` runs it
def test_train_and_evaluate_fine_tunes_from_init_from(tmp_path, run_data):
    from dmd_jax.checkpoints import save_weights
    from dmd_jax.data.training_sets import training_sets
    from dmd_jax.model import init_params

    # A source unlike the run's own init (another seed).
    source = tmp_path / "source.msgpack"
    cfg = _run_config(run_data, eval_meshes_per_split=0)  # no evaluation to compile
    save_weights(source, init_params(cfg.model, jax.random.PRNGKey(7)), cfg)
    cfg = cfg.with_edits({"train": {"init_from": str(source)}})
    tuned = train.train_and_evaluate(cfg, tmp_path / "b", progress=False)
    # The same as handing `train` the source's params.
    by_hand = train.train(
        cfg.with_edits({"train": {"init_from": None}}),
        pipeline.make_examples(training_sets(cfg.data, seed=0).train),
        tmp_path / "c",
        progress=False,
        init_params=train.init_params_from(source, cfg),
        pad_to="largest",
    )
    assert tuned["step"] == by_hand["step"] == 3
    losses = {d: [r["loss"] for r in _log(tmp_path / d) if r["kind"] == "train"] for d in "bc"}
    assert losses["b"] == losses["c"]
    for a, b in zip(_leaves(tuned), _leaves(by_hand), strict=True):
        np.testing.assert_array_equal(a, b)
    bad = cfg.with_edits({"train": {"init_from": str(tmp_path / "missing.msgpack")}})
    with pytest.raises(FileNotFoundError):
        train.train_and_evaluate(bad, tmp_path / "d", progress=False)


def test_train_and_evaluate_needs_a_dataset(tmp_path):
    with pytest.raises(ValueError, match="data.dataset_dir"):
        train.train_and_evaluate(config.preset("test"), tmp_path, progress=False)
    cfg = config.preset("test").with_edits({"data": {"dataset_dir": str(tmp_path / "none")}})
    with pytest.raises(FileNotFoundError):
        train.train_and_evaluate(cfg, tmp_path / "run", progress=False)
    with pytest.raises(ValueError, match="pad must be one of"):
        train.train_and_evaluate(cfg, tmp_path / "run", pad="smallest")


class _Record(train.TrainHook):
    def __init__(self):
        self.before, self.after = [], []

    def before_step(self, step, batch):
        self.before.append(step)
        return batch

    def after_step(self, step, metrics):
        self.after.append((step, float(metrics["loss"])))


def test_hooks_see_every_step_and_a_stop_checkpoints(tmp_path):
    cfg = config.preset("test").with_edits(TINY).with_edits({"train": {"log_every": 0}})
    examples = pipeline.make_examples([icosphere(1), tetrahedron()])
    seen = _Record()
    out = train.train(cfg, examples, tmp_path, progress=False, hooks=[seen, train.StopAfter(2)])
    # Both hooks ran at every step; the stop came after the second.
    assert out["step"] == 2 and seen.before == [0, 1] and [s for s, _ in seen.after] == [0, 1]
    rows = _log(tmp_path)
    assert [(r["step"], r["loss"]) for r in rows] == [(2, seen.after[1][1])]
    seen = _Record()
    out = train.train(cfg, examples, tmp_path, progress=False, hooks=[seen])
    assert out["step"] == 4 and seen.before == [2, 3]  # resumed from the stop's checkpoint
    with pytest.raises(train.NonFiniteLossError, match="at step 1"):
        train.train(cfg, examples, tmp_path / "nan", progress=False, hooks=[train.InjectNaN(1)])
    with pytest.raises(ValueError, match="at least 1 step"):
        train.StopAfter(0)


@pytest.mark.slow  # measured 15-50 s on 2 idle cores; `make test-slow` runs it
def test_resume_reads_a_config_json_written_before_new_fields(tmp_path):
    """A run whose `config.json` predates a setting resumes; one whose recorded setting
    differs from this run's does not."""
    cfg = config.preset("test").with_edits(TINY)
    examples = pipeline.make_examples([icosphere(1), tetrahedron()])
    train.train(cfg, examples, tmp_path, progress=False, hooks=[train.StopAfter(1)])
    path = tmp_path / "config.json"
    stored = json.loads(path.read_text())
    del stored["data"]["real_root"], stored["train"]["init_from"]
    path.write_text(json.dumps(stored))
    moved = cfg.with_edits({"data": {"real_root": "elsewhere"}})
    assert train.train(moved, examples, tmp_path, progress=False)["step"] == 4
    other = cfg.with_edits({"data": {"dataset_dir": "elsewhere"}})
    with pytest.raises(ValueError, match="different config"):
        train.train(other, examples, tmp_path, progress=False)


def test_run_settings_are_config_fields():
    d = config.DataConfig(dataset_dir="ds", real_root="real", eval_meshes_per_split=0, **REAL)
    assert config.DataConfig.from_json(d.to_json()) == d
    t = config.TrainConfig(init_from="w.msgpack")
    assert config.TrainConfig.from_dict(t.to_dict()) == t
    # The defaults are what `dmd-jax train` did before they were fields.
    plain = config.DataConfig()
    assert (plain.dataset_dir, plain.real_root, plain.eval_meshes_per_split) == (None, None, 8)
    assert (plain.real_patch_faces, plain.real_faces_per_patch) == (6000, 12000)
    assert (plain.real_patches_per_mesh, plain.real_val_patch_faces) == (8, 4000)
    assert plain.real_val_patches_per_mesh == 1 and config.TrainConfig().init_from is None
    for bad, match in [
        ({"eval_meshes_per_split": -1}, "eval_meshes_per_split must be an integer >= 0"),
        ({"real_patch_faces": 0}, "real_patch_faces must be an integer >= 1"),
        ({"real_root": ""}, "real_root must be a path or null"),
        ({"dataset_dir": 3}, "dataset_dir must be a path or null"),
    ]:
        with pytest.raises(ValueError, match=match):
            config.DataConfig(**bad)
    with pytest.raises(ValueError, match="init_from must be a path"):
        config.TrainConfig(init_from="")


def test_train_flags_only_set_config_fields(capsys):
    from dmd_jax import cli

    def cfg(*argv):
        args = cli.build_parser().parse_args(["train", "--data", "ds", "--workdir", "w", *argv])
        return cli._train_config(args)

    plain = cfg("--preset", "test")
    assert plain == config.preset("test").with_edits({"data": {"dataset_dir": "ds"}})
    flags = cfg("--eval-meshes", "3", "--real-meshes", "real", "--init-from", "w.msgpack")
    assert (flags.data.eval_meshes_per_split, flags.data.real_root) == (3, "real")
    assert flags.train.init_from == "w.msgpack"
    # A flag not given leaves a --set edit of its field alone.
    edited = cfg("--set", "data.eval_meshes_per_split=2", "data.real_patch_faces=500")
    assert (edited.data.eval_meshes_per_split, edited.data.real_patch_faces) == (2, 500)
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["train", "--help"])
    # The help's number is the constant `--pad auto` goes by.
    assert f"at most {train.AUTO_PAD_MAX_STEPS} steps" in " ".join(capsys.readouterr().out.split())


def test_training_sets_read_meshes_without_jax():
    """The host half of the input pipeline imports neither JAX nor Flax."""
    import subprocess
    import sys

    code = "import sys, dmd_jax.data.training_sets; print({'jax', 'flax'} & set(sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "set()"


# ---------------------------------------------------------------- unrolled passes


def _one_group(cfg):
    examples = pipeline.make_examples([icosphere(1)])
    batch = pipeline.training_batch(examples, 0, batch_size=1, seed=0, noise=cfg.noise)
    return jax.tree.map(lambda x: jnp.asarray(x[0]), (batch.noisy, batch.clean, batch.graph))


def test_passes_add_each_pass_terms_with_the_gradient_stopped_between_them():
    """`train.passes=2` scores the network on the noisy mesh and on its own output: the
    terms are the sums of two one-pass calls, the second fed the first's output, and no
    gradient reaches the first pass through the second's input."""
    cfg1 = config.preset("test").with_edits(TINY)
    cfg2 = cfg1.with_edits({"train": {"passes": 2}})
    noisy, clean, graph = _one_group(cfg1)
    model = train.DMDNet(cfg1.model)
    params = train._init_program(cfg1.model)(
        {"params": jax.random.PRNGKey(0), "dropout": jax.random.PRNGKey(0)}, noisy, graph
    )["params"]
    loss = train.phase_loss(cfg1, "all")

    # Jitted: run eagerly, every primitive of the model compiles on its own (~50 s).
    @jax.jit
    def one(p, x):
        return train.loss_terms(model, cfg1, p, x, clean, graph, loss=loss)

    @jax.jit
    def two(p):
        return train.loss_terms(model, cfg2, p, noisy, clean, graph, loss=loss)

    first_out = jax.jit(lambda p: model.apply({"params": p}, noisy, graph, deterministic=True)[0])(
        params
    )
    by_hand = jax.tree.map(jnp.add, one(params, noisy), one(params, first_out))
    both = two(params)
    assert set(both) == set(by_hand)
    for name in both:
        np.testing.assert_allclose(both[name].total, by_hand[name].total, rtol=1e-5)
        assert int(both[name].count) == 2 * int(one(params, noisy)[name].count)

    def total(terms):
        return sum(t.mean() for t in terms.values())

    # The gradient: the first call's own, plus the second's with its input held fixed.
    grads = jax.jit(jax.grad(lambda p: total(two(p))))(params)
    want = jax.jit(
        jax.grad(lambda p: total(jax.tree.map(jnp.add, one(p, noisy), one(p, first_out))))
    )(params)
    for a, b in zip(jax.tree.leaves(grads), jax.tree.leaves(want), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-7)


def test_crease_weight_weights_the_normal_terms_by_the_clean_creases():
    """`loss.crease_weight`: the normal and face-normal terms become means weighted by the
    clean mesh's crease faces (`losses.crease_face_mask`); other terms do not change."""
    import trimesh

    from dmd_jax import losses

    box = trimesh.creation.box().subdivide().subdivide()
    cfg = config.preset("test").with_edits(TINY)
    examples = pipeline.make_examples([(np.asarray(box.vertices), np.asarray(box.faces))])
    batch = pipeline.training_batch(examples, 0, batch_size=1, seed=0, noise=cfg.noise)
    noisy, clean, graph = jax.tree.map(
        lambda x: jnp.asarray(x[0]), (batch.noisy, batch.clean, batch.graph)
    )
    model = train.DMDNet(cfg.model)
    params = train._init_program(cfg.model)(
        {"params": jax.random.PRNGKey(0), "dropout": jax.random.PRNGKey(0)}, noisy, graph
    )["params"]
    plain, weighted = (
        jax.jit(lambda p, c=c: train.loss_terms(model, c, p, noisy, clean, graph, loss=c.loss))(
            params
        )
        for c in (cfg, cfg.with_edits({"loss": {"crease_weight": 4.0}}))
    )
    assert set(plain) == set(weighted) and {"normal", "face_normal"} <= set(plain)
    crease = np.asarray(
        losses.crease_face_mask(clean, graph.faces, graph.face_senders, graph.face_receivers)
    )
    assert 0 < crease[np.asarray(graph.face_mask)].sum() < np.asarray(graph.face_mask).sum()
    out = jax.jit(lambda p: model.apply({"params": p}, noisy, graph, deterministic=True)[0])(params)
    want = losses.normal_term(
        out, clean, graph.faces, face_mask=graph.face_mask, face_weight=np.where(crease, 4.0, 1.0)
    )
    np.testing.assert_allclose(weighted["normal"].total, want.total, rtol=1e-4)
    for name in plain:
        assert int(plain[name].count) == int(weighted[name].count)
        if name in ("normal", "face_normal"):
            assert abs(float(plain[name].total) - float(weighted[name].total)) > 1e-4
        else:
            np.testing.assert_allclose(plain[name].total, weighted[name].total, rtol=1e-6)


def test_evaluation_runs_the_trained_passes():
    cfg = config.preset("test").with_edits(TINY).with_edits({"train": {"passes": 3}})
    noisy, _, graph = _one_group(cfg)
    trainer = train.Trainer(cfg)
    params = train._init_program(cfg.model)(
        {"params": jax.random.PRNGKey(1), "dropout": jax.random.PRNGKey(1)}, noisy, graph
    )["params"]
    apply = jax.jit(lambda x: trainer.model.apply({"params": params}, x, graph, deterministic=True))
    x = noisy
    for _ in range(3):
        x = apply(x)[0]
    np.testing.assert_allclose(trainer._predict(params, noisy, graph)[0], x, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("passes", [0, config.MAX_TRAIN_PASSES + 1, 1.5, True])
def test_passes_are_bounded(passes):
    with pytest.raises(ValueError, match="passes"):
        config.preset("test").with_edits({"train": {"passes": passes}})

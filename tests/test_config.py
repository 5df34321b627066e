"""Configs: JSON round trips, strict parsing, validation, pytree behaviour, presets and
the ablation tables (checked against the paper's appendix D)."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import pytest

from dmd_jax.config import (
    VARIANT_NAMES,
    VARIANTS,
    DataConfig,
    ExperimentConfig,
    LossConfig,
    ModelConfig,
    NoiseConfig,
    TrainConfig,
    preset,
    variant_config,
)
from experiments.ablations import ABLATIONS, ablation_config


def all_configs():
    out = [preset(name) for name in ("paper", "small", "test")]
    for study, rows in ABLATIONS.items():
        for row in rows:
            out.append(ablation_config(preset("test"), study, row))
    out.append(
        ExperimentConfig(
            noise=NoiseConfig(
                kinds=("gaussian", "impulse"),
                canonical_levels=(("gaussian", (0.01, 0.02)), ("impulse", (0.1,))),
                edge_levels=(0.2, 0.4),
            ),
            data=DataConfig(source="folder", root="/data/meshes", categories=("a", "b")),
            model=ModelConfig(transformer_width=16),
        )
    )
    return out


@pytest.mark.parametrize("cfg", all_configs(), ids=lambda c: c.name)
def test_json_round_trip(cfg):
    text = cfg.to_json()
    back = ExperimentConfig.from_json(text)
    assert back == cfg
    assert hash(back) == hash(cfg)
    # Plain JSON types only (lists, not tuples), so json.dumps(to_dict()) is the format.
    assert json.loads(json.dumps(cfg.to_dict())) == cfg.to_dict()


def test_from_dict_fills_defaults_and_nested_sections():
    cfg = ExperimentConfig.from_dict({"model": {"width": 16}, "train": {"lr": 1}})
    assert cfg.model == ModelConfig(width=16)
    assert cfg.train.lr == 1.0 and isinstance(cfg.train.lr, float)
    assert cfg.loss == LossConfig()


@pytest.mark.parametrize(
    "data,match",
    [
        ({"modle": {}}, r"unknown key\(s\) \['modle'\]"),
        ({"model": {"widht": 8}}, r"ModelConfig: unknown key\(s\) \['widht'\]"),
        ({"model": {"width": "8"}}, "ModelConfig.width: expected an integer"),
        ({"model": {"width": 8.0}}, "ModelConfig.width: expected an integer"),
        ({"model": {"width": True}}, "ModelConfig.width: expected an integer"),
        ({"model": {"attention": 1}}, "ModelConfig.attention: expected true/false"),
        ({"model": {"variant": "fgt9"}}, "variant must be one of"),
        ({"model": {"dropout": 1.0}}, r"dropout must lie in \[0, 1\)"),
        ({"model": {"depth": 0}}, "depth must be an integer >= 1"),
        ({"model": {"transformer_width": "x"}}, "transformer_width: expected an integer"),
        ({"model": 3}, "ModelConfig: expected a dict"),
        ({"loss": {"normal": -1.0}}, "loss weight normal"),
        ({"train": {"scheme": "joined"}}, "scheme must be one of"),
        ({"train": {"schedule": "warmup_cosine"}}, "schedule must be one of"),
        ({"noise": {"kinds": ["gaussian", "pink"]}}, "noise kind must be one of"),
        ({"noise": {"kinds": "gaussian"}}, "expected a list"),
        ({"noise": {"canonical_levels": [["gaussian"]]}}, "expected 2 items"),
        ({"data": {"source": "folder"}}, "needs a root directory"),
        ({"name": 3}, "ExperimentConfig.name: expected a string"),
    ],
)
def test_from_dict_is_strict(data, match):
    with pytest.raises(ValueError, match=match):
        ExperimentConfig.from_dict(data)


def test_from_json_rejects_invalid_json():
    with pytest.raises(ValueError, match="invalid JSON"):
        ExperimentConfig.from_json("{model: }")


def test_configs_are_frozen_static_pytrees():
    cfg = preset("small")
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.model.width = 3
    assert jax.tree.leaves(cfg) == []
    # Hashable, so a config can be a static argument of jit; equal configs share a trace.
    traces = []

    def f(x, model):
        traces.append(model.width)
        return x * model.width

    g = jax.jit(f, static_argnums=1)
    assert float(g(jnp.ones(()), ModelConfig(width=5))) == 5.0
    g(jnp.ones(()), ModelConfig(width=5))
    assert float(g(jnp.ones(()), ModelConfig(width=6))) == 6.0
    assert traces == [5, 6]


def test_with_edits_is_nested_and_strict():
    cfg = preset("test").with_edits({"model": {"depth": 4}, "train": {"steps": 7}})
    assert cfg.model.depth == 4 and cfg.train.steps == 7
    assert cfg.model.width == preset("test").model.width
    with pytest.raises(ValueError, match="unknown field"):
        cfg.with_edits({"model": {"dept": 4}})
    with pytest.raises(ValueError, match="depth must be"):
        cfg.with_edits({"model": {"depth": 0}})


def test_presets():
    assert preset("paper").model.width == 512
    assert preset("paper").model.variant == "fgt8"
    assert preset("paper").model.depth == 2
    assert preset("paper").model.fe_two_streams == 2
    paper_train = preset("paper").train
    assert (paper_train.lr, paper_train.b1, paper_train.b2) == (1e-4, 0.9, 0.999)
    assert preset("test").model.width == 8
    assert preset("small").model.width == 32
    # The paper preset keeps the paper's reading; small is the resolution-free recipe.
    assert (preset("paper").model.encoding, preset("paper").model.head) == ("xyz", "offset")
    assert (preset("small").model.encoding, preset("small").model.head) == ("local", "normal")
    with pytest.raises(ValueError, match="unknown preset"):
        preset("huge")


def test_loss_config_defaults_are_the_paper_weights():
    c = LossConfig()
    # Paper section 3.3: λ_V = 1, λ_N = 0.2, λ_κ = 0.01, λ_C = 0.05, λ_FE = 1.
    assert (c.vertex, c.normal, c.curvature, c.chamfer, c.feature) == (1.0, 0.2, 0.01, 0.05, 1.0)
    assert (c.gamma_h, c.gamma_g) == (1e-6, 1.0)
    ones = LossConfig.all_ones()
    assert (ones.vertex, ones.normal, ones.curvature, ones.chamfer, ones.feature) == (1.0,) * 5


def test_train_config_derived_values():
    t = TrainConfig(steps=10, two_phase_split=0.3)
    assert t.two_phase_fe_steps == 3
    assert t.learning_rate == t.lr
    assert TrainConfig(steps=2, two_phase_split=0.01).two_phase_fe_steps == 1


def test_variant_table_covers_the_paper_structure_ablation():
    # Appendix D, "Structure Ablation": seven variants.
    assert list(VARIANTS) == ["FGT-8", "FGT-3", "W/O T", "MT", "DO-2S", "DO-1S", "FGT-1S"]
    assert sorted(v["variant"] for v in VARIANTS.values()) == sorted(VARIANT_NAMES)
    base = ModelConfig()
    expect = {
        # name: (feature extractor, transformer, FE two-stream, denoiser two-stream, rows)
        "FGT-8": (True, True, True, True, 8),
        "FGT-3": (True, True, True, True, 3),
        "W/O T": (True, False, True, True, 8),
        "MT": (True, True, True, True, 8),
        "DO-2S": (False, False, True, True, 8),
        "DO-1S": (False, False, True, False, 8),
        "FGT-1S": (True, True, False, False, 8),
    }
    for name, (fe, tr, fe2, den2, rows) in expect.items():
        cfg = variant_config(base, name)
        assert cfg.uses_feature_extractor == fe
        assert cfg.uses_transformer == tr
        assert cfg.denoiser_two_stream == den2
        if fe:
            assert cfg.fe_two_stream == fe2
            assert cfg.transform_in_dim == rows
        assert cfg.n_transforms == (base.mt_transforms if name == "MT" else 1)
    assert variant_config(base, "fgt3") == variant_config(base, "FGT-3")
    with pytest.raises(ValueError, match="unknown variant"):
        variant_config(base, "FGT-9")


def test_every_config_field_is_read():
    """Every field is read by the code outside `dmd_jax.config` (directly, or through a
    derived property of `config/sections.py` that is): a field nothing reads is a
    setting that silently does nothing.

    `DataConfig` is left out: it records the dataset of a run (the ablation runs fill it
    in, `experiments.studies.AblatePreset.data_edits`) and nothing reads it yet; their
    result directories are keyed by a hash of the whole config, so it stays until the
    dataset is built from it.
    """
    import ast
    from pathlib import Path

    import dmd_jax

    package = Path(dmd_jax.__file__).parent
    read = set()
    for path in package.rglob("*.py"):
        if path.parent.name != "config":
            read |= {
                n.attr
                for n in ast.walk(ast.parse(path.read_text()))
                if isinstance(n, ast.Attribute)
            }
    # The loss reads its weights by name (`getattr(weights, name)` over `losses.TERMS`).
    from dmd_jax.losses import TERMS

    read |= set(TERMS)
    # Properties of the config classes read the fields they derive from.
    for node in ast.walk(ast.parse((package / "config" / "sections.py").read_text())):
        if isinstance(node, ast.FunctionDef) and node.name in read:
            read |= {n.attr for n in ast.walk(node) if isinstance(n, ast.Attribute)}
    unread = []
    for cls in (ModelConfig, LossConfig, TrainConfig, NoiseConfig, ExperimentConfig):
        unread += [
            f"{cls.__name__}.{f.name}" for f in dataclasses.fields(cls) if f.name not in read
        ]
    assert not unread, f"config fields nothing reads: {unread}"

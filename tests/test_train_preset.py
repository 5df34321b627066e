"""`dmd-jax train --preset test` as a new user runs it: a tiny procedural dataset, one
compiled training program, a line when it compiles, and one closing line that compares
the trained model with its noisy input (issue 16)."""

from __future__ import annotations

import re
import subprocess
import sys
import time

import pytest

from dmd_jax.cli import _parse_edits
from dmd_jax.config import preset


def _cli(*args: str, cwd) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "dmd_jax.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=900,
    )


@pytest.mark.slow
def test_test_preset_trains_a_tiny_dataset_and_beats_its_noisy_input(tmp_path):
    made = _cli(
        "make-dataset", "--out", "tiny", "--per-category", "2", "--no-progress", cwd=tmp_path
    )
    assert made.returncode == 0, made.stderr
    start = time.perf_counter()
    run = _cli(
        "train",
        "--data",
        "tiny",
        "--workdir",
        "run",
        "--preset",
        "test",
        "--no-progress",
        cwd=tmp_path,
    )
    wall = time.perf_counter() - start
    assert run.returncode == 0, run.stderr
    lines = run.stdout.strip().splitlines()
    # Says when it compiles, and compiles the training step once (one padded shape).
    compiled = [x for x in lines if x.startswith("compiled the training step")]
    assert len(compiled) == 1 and "1 program(s) so far" in compiled[0], lines
    assert sum(x.startswith("evaluated ") and "compiling 1 " in x for x in lines) == 1, lines
    # Ends with one line: the model against its noisy input, per evaluation set.
    last = lines[-1]
    found = re.findall(r"(\w+) normal error ([\d.]+)° vs noisy ([\d.]+)° \(([+-]\d+) %\)", last)
    assert {split for split, *_ in found} == {"test_intra", "test_inter"}, last
    for _split, model, noisy, _change in found:
        assert float(model) < float(noisy), last
    print(f"train --preset test: {wall:.0f} s wall; {last}")


def test_the_test_preset_is_the_small_recipe_at_a_tiny_width():
    small, test = preset("small"), preset("test")
    assert test.model.width == 8 and test.model.width < small.model.width
    assert (test.model.encoding, test.model.head) == (small.model.encoding, small.model.head)
    assert test.noise == small.noise
    assert test.loss == small.loss.replace(chamfer_block=test.loss.chamfer_block)
    assert test.train.lr == small.train.lr and test.train.schedule == small.train.schedule


def test_set_with_a_wrong_type_names_the_field_and_the_type():
    cfg = preset("test")
    # Not JSON, so `--set` keeps it as the string "(0.1,0.2)".
    edits = _parse_edits(["noise.edge_levels=(0.1,0.2)"])
    with pytest.raises(ValueError, match=r"noise\.edge_levels: expected a list of numbers"):
        cfg.with_edits(edits)
    with pytest.raises(ValueError, match=r"train\.steps: expected an integer, got '10x'"):
        cfg.with_edits(_parse_edits(["train.steps=10x"]))
    with pytest.raises(ValueError, match=r"model\.encoding: expected a string, got 3"):
        cfg.with_edits({"model": {"encoding": 3}})
    # What from_dict accepts, with_edits accepts, converted the same way.
    good = cfg.with_edits(_parse_edits(["noise.edge_levels=[0.1,1]", "train.lr=1"]))
    assert good.noise.edge_levels == (0.1, 1.0) and isinstance(good.train.lr, float)
    assert good == type(cfg).from_dict(
        {
            **cfg.to_dict(),
            "noise": {**cfg.noise.to_dict(), "edge_levels": [0.1, 1]},
            "train": {**cfg.train.to_dict(), "lr": 1},
        }
    )

"""The `dmd-jax` command line end to end, the demo and the sota-lite script.

Commands run in-process through `dmd_jax.cli.main` (one JAX start-up for the module);
one test runs the real entry point in a subprocess to check exit codes and stderr as a
shell sees them. All meshes are the same icosphere size, so the tiny model compiles once.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from conftest import icosphere
from test_inference import TINY_CONFIG, tiny_params

from dmd_jax import baselines, checkpoints, inference
from dmd_jax.cli import main
from dmd_jax.config import preset
from dmd_jax.io import load_mesh, save_mesh
from dmd_jax.mesh import mean_edge_length
from dmd_jax.metrics import mesh_metrics, metrics_legend
from dmd_jax.policy import DenoisePolicy

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def weights(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("weights") / "tiny.msgpack"
    return checkpoints.save_weights(path, tiny_params(), TINY_CONFIG, {"note": "tiny"})


@pytest.fixture(scope="module")
def files(tmp_path_factory, weights):
    """clean.obj -> noisy.obj (add-noise) -> dmd.obj (denoise), through the CLI."""
    d = tmp_path_factory.mktemp("cli")
    v, f = icosphere(2)
    save_mesh(d / "clean.obj", v, f)
    assert (
        main(
            [
                "add-noise",
                str(d / "clean.obj"),
                "-o",
                str(d / "noisy.obj"),
                "--level",
                "0.2",
                "--units",
                "edge",
                "--seed",
                "3",
            ]
        )
        == 0
    )
    assert (
        main(["denoise", str(d / "noisy.obj"), "-o", str(d / "dmd.obj"), "--weights", str(weights)])
        == 0
    )
    return d


def run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def assert_png(path: Path) -> None:
    from PIL import Image

    assert path.read_bytes()[:8] == PNG_SIGNATURE
    with Image.open(path) as image:
        image.verify()
    with Image.open(path) as image:
        assert image.format == "PNG" and image.width > 0 and image.height > 0


def assert_one_line_error(code: int, err: str, *fragments: str) -> None:
    assert code != 0
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("dmd-jax ") and "error:" in lines[0]
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


def test_add_noise_level_and_seed(files, capsys, tmp_path):
    clean_v, f = load_mesh(files / "clean.obj")
    noisy_v, f2 = load_mesh(files / "noisy.obj")
    np.testing.assert_array_equal(f, f2)
    # σ = 0.2 mean edge lengths; 486 samples give the std to about 3.2 % (1 sd).
    sigma = np.std(noisy_v - clean_v)
    assert sigma == pytest.approx(0.2 * mean_edge_length(clean_v, f), rel=0.15)
    common = ["add-noise", files / "clean.obj", "--level", "0.2", "--units", "edge"]
    assert run(capsys, *common, "-o", tmp_path / "same.obj", "--seed", "3")[0] == 0
    assert run(capsys, *common, "-o", tmp_path / "other.obj", "--seed", "4")[0] == 0
    np.testing.assert_array_equal(load_mesh(tmp_path / "same.obj")[0], noisy_v)
    assert np.abs(load_mesh(tmp_path / "other.obj")[0] - noisy_v).max() > 0.01 * sigma


def test_denoise_matches_the_python_api(files, weights):
    noisy_v, f = load_mesh(files / "noisy.obj")
    out_v, f2 = load_mesh(files / "dmd.obj")
    np.testing.assert_array_equal(f, f2)
    # OBJ keeps float64 to 17 significant digits (1e-17 absolute below 0.1).
    np.testing.assert_allclose(
        out_v, inference.denoise(noisy_v, f, weights), rtol=1e-15, atol=1e-16
    )


def test_evaluate_json_matches_mesh_metrics(files, capsys):
    code, out, _ = run(
        capsys,
        "evaluate",
        "--gt",
        files / "clean.obj",
        "--mesh",
        files / "noisy.obj",
        files / "dmd.obj",
        "--json",
    )
    assert code == 0
    rows = json.loads(out)
    gt_v, f = load_mesh(files / "clean.obj")
    assert [Path(r["mesh"]).name for r in rows] == ["noisy.obj", "dmd.obj"]
    for row in rows:
        expected = mesh_metrics(load_mesh(row["mesh"])[0], gt_v, f)
        for name in ("vertex", "normal_deg", "chamfer"):
            assert row[name] == pytest.approx(expected[name], rel=1e-12)
    assert rows[0]["normal_deg"] > 1.0  # the noise is visible in the normals


def test_evaluate_table(files, capsys):
    code, out, _ = run(
        capsys, "evaluate", "--gt", files / "clean.obj", "--mesh", files / "noisy.obj"
    )
    assert code == 0
    header, row, blank, legend = out.strip().splitlines()
    # The vocabulary of dmd_jax.metrics: the paper's per-coordinate vertex error first.
    assert header.split()[:3] == ["mesh", "vertex", "(×1e-4)"]
    assert "normal (°)" in header and "chamfer (×1e-4)" in header
    assert row.split()[0].endswith("noisy.obj") and blank == ""
    assert legend == metrics_legend()
    gt_v, f = load_mesh(files / "clean.obj")
    m = mesh_metrics(load_mesh(files / "noisy.obj")[0], gt_v, f)
    assert float(row.split()[1]) == pytest.approx(m["vertex_per_coord"] * 1e4, abs=1e-3)


def test_render_png(files, capsys, tmp_path):
    png = tmp_path / "cmp.png"
    code, out, _ = run(
        capsys,
        "render",
        files / "noisy.obj",
        files / "dmd.obj",
        "-o",
        png,
        "--gt",
        files / "clean.obj",
        "--titles",
        "noisy,dmd",
    )
    assert code == 0 and str(png) in out
    assert_png(png)


def test_method_taubin(files, capsys, tmp_path):
    out_path = tmp_path / "taubin.off"
    code, out, _ = run(capsys, "denoise", files / "noisy.obj", "-o", out_path, "--method", "taubin")
    assert code == 0 and "taubin" in out
    noisy_v, f = load_mesh(files / "noisy.obj")
    got, _ = load_mesh(out_path)
    np.testing.assert_allclose(got, baselines.run_baseline("taubin", noisy_v, f), atol=1e-12)
    clean_v, _ = load_mesh(files / "clean.obj")
    assert (
        mesh_metrics(got, clean_v, f)["normal_deg"]
        < mesh_metrics(noisy_v, clean_v, f)["normal_deg"]
    )


def test_unknown_method(files, capsys, tmp_path):
    code, _, err = run(
        capsys, "denoise", files / "noisy.obj", "-o", tmp_path / "x.obj", "--method", "magic"
    )
    assert_one_line_error(code, err, "magic")
    assert not (tmp_path / "x.obj").exists()


def test_iterations_flag(files, capsys, tmp_path, weights):
    out_path = tmp_path / "dmd2.obj"
    code, _, _ = run(
        capsys,
        "denoise",
        files / "noisy.obj",
        "-o",
        out_path,
        "--weights",
        weights,
        "--iterations",
        "2",
    )
    assert code == 0
    noisy_v, f = load_mesh(files / "noisy.obj")
    expected = inference.denoise(noisy_v, f, weights, iterations=2)
    np.testing.assert_allclose(load_mesh(out_path)[0], expected, rtol=1e-15, atol=1e-16)
    code, _, err = run(
        capsys,
        "denoise",
        files / "noisy.obj",
        "-o",
        tmp_path / "dmd0.obj",
        "--weights",
        weights,
        "--iterations",
        "0",
    )
    assert_one_line_error(code, err, "iterations")
    assert not (tmp_path / "dmd0.obj").exists()


def test_presmooth_flag(files, capsys, tmp_path, weights):
    out_path = tmp_path / "smoothed.obj"
    args = ("denoise", files / "noisy.obj", "-o", out_path, "--weights", weights)
    code, out, err = run(capsys, *args, "--presmooth", "3")
    assert code == 0, err
    assert "after 3 Laplacian steps" in out
    noisy_v, f = load_mesh(files / "noisy.obj")
    expected = inference.denoise(noisy_v, f, weights, presmooth=3)
    np.testing.assert_allclose(load_mesh(out_path)[0], expected, rtol=1e-15, atol=1e-16)
    bad = ("denoise", files / "noisy.obj", "-o", tmp_path / "bad.obj", "--weights", weights)
    code, _, err = run(capsys, *bad, "--presmooth", "-1")
    assert_one_line_error(code, err, "presmooth")
    code, _, err = run(capsys, *bad, "--presmooth", "lots")
    assert_one_line_error(code, err, "or 'rule'")
    # 'rule': the roughness rule of the weights' policy, as by default.
    code, out, err = run(capsys, *args, "--presmooth", "rule", "--overwrite")
    assert code == 0, err
    expected = inference.denoise(noisy_v, f, weights, presmooth="rule")
    np.testing.assert_allclose(load_mesh(out_path)[0], expected, rtol=1e-15, atol=1e-16)
    code, _, err = run(
        capsys,
        "denoise",
        files / "noisy.obj",
        "-o",
        tmp_path / "bnf.obj",
        "--method",
        "bnf",
        "--presmooth",
        "2",
    )
    assert_one_line_error(code, err, "presmooth")
    assert not (tmp_path / "bad.obj").exists() and not (tmp_path / "bnf.obj").exists()


def test_refuses_to_overwrite_the_input(files, capsys, weights):
    before = (files / "noisy.obj").read_bytes()
    code, _, err = run(
        capsys,
        "denoise",
        files / "noisy.obj",
        "-o",
        files / "noisy.obj",
        "--weights",
        weights,
        "--overwrite",
    )
    assert_one_line_error(code, err, "input")
    code, _, err = run(
        capsys,
        "add-noise",
        files / "noisy.obj",
        "-o",
        files / "noisy.obj",
        "--level",
        "0.1",
        "--overwrite",
    )
    assert_one_line_error(code, err, "input")
    assert (files / "noisy.obj").read_bytes() == before


def test_refuses_to_overwrite_an_existing_output(files, capsys, weights, tmp_path):
    target = tmp_path / "existing.obj"
    target.write_text("keep me\n")
    for argv in (
        ["denoise", files / "noisy.obj", "-o", target, "--weights", weights],
        ["denoise", files / "noisy.obj", "-o", target, "--method", "taubin"],
        ["add-noise", files / "clean.obj", "-o", target, "--level", "0.1"],
    ):
        code, _, err = run(capsys, *argv)
        assert_one_line_error(code, err, "already exists", "--overwrite")
        assert target.read_text() == "keep me\n"
    png = tmp_path / "existing.png"
    png.write_bytes(b"keep")
    code, _, err = run(capsys, "render", files / "noisy.obj", "-o", png)
    assert_one_line_error(code, err, "already exists")
    assert png.read_bytes() == b"keep"
    # With --overwrite the same command replaces the file.
    code, _, _ = run(
        capsys, "denoise", files / "noisy.obj", "-o", target, "--method", "taubin", "--overwrite"
    )
    assert code == 0 and load_mesh(target)[0].shape == (162, 3)


def test_missing_input_and_bad_weights(files, capsys, tmp_path):
    code, _, err = run(capsys, "denoise", tmp_path / "absent.obj", "-o", tmp_path / "o.obj")
    assert_one_line_error(code, err, "absent.obj")
    bad = tmp_path / "bad.msgpack"
    bad.write_bytes(b"\x00garbage")
    code, _, err = run(
        capsys, "denoise", files / "noisy.obj", "-o", tmp_path / "o.obj", "--weights", bad
    )
    assert_one_line_error(code, err, "bad.msgpack")
    code, _, err = run(
        capsys,
        "denoise",
        files / "noisy.obj",
        "-o",
        tmp_path / "o.obj",
        "--weights",
        tmp_path / "none.msgpack",
    )
    assert_one_line_error(code, err, "none.msgpack")
    assert not (tmp_path / "o.obj").exists()


def test_info(capsys):
    from dmd_jax.model import param_count

    code, out, _ = run(capsys, "info")
    assert code == 0 and out.startswith("dmd_jax ") and "jax " in out
    code, out, _ = run(capsys, "info", "--preset", "test")
    assert code == 0
    total = [line for line in out.splitlines() if line.strip().startswith("total")]
    assert int(total[0].split()[1].replace(",", "")) == param_count(preset("test").model)


def test_entry_point_subprocess(files, tmp_path):
    # The real process: exit status and a one-line stderr as a shell sees them.
    cmd = [sys.executable, "-m", "dmd_jax.cli"]
    info = subprocess.run([*cmd, "info"], capture_output=True, text=True, timeout=120)
    assert info.returncode == 0 and info.stdout.startswith("dmd_jax ")
    target = tmp_path / "exists.obj"
    target.write_text("keep\n")
    proc = subprocess.run(
        [*cmd, "add-noise", str(files / "clean.obj"), "-o", str(target), "--level", "0.1"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert_one_line_error(proc.returncode, proc.stderr, "already exists")
    assert proc.returncode == 2 and target.read_text() == "keep\n"
    # `console` skips the interpreter's teardown: the file is whole and stdout flushed.
    out = tmp_path / "noisy.obj"
    proc = subprocess.run(
        [*cmd, "add-noise", str(files / "clean.obj"), "-o", str(out), "--level", "0.1"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0 and str(out) in proc.stdout + proc.stderr
    assert load_mesh(out)[1].shape == load_mesh(files / "clean.obj")[1].shape


def test_console_exits_with_the_code_of_main(monkeypatch):
    import dmd_jax.cli as cli

    exits = []
    monkeypatch.setattr(cli, "main", lambda: 3)
    monkeypatch.setattr(cli.os, "_exit", exits.append)
    cli.console()
    assert exits == [3]


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory, weights):
    out = tmp_path_factory.mktemp("demo") / "out"
    assert main(["demo", "--out", str(out), "--weights", str(weights)]) == 0
    return out


def test_demo_writes_meshes_metrics_and_png(demo_dir):
    from dmd_jax import demo

    assert {p.name for p in demo_dir.iterdir()} == set(demo.MESH_FILES.values()) | {
        demo.METRICS_FILE,
        demo.RENDER_FILE,
    }
    assert_png(demo_dir / demo.RENDER_FILE)
    from PIL import Image

    from dmd_jax.render import white_fraction

    # Shaded, zoom and error rows that fill the figure (the old picture: 1760 × 385 px,
    # 82 % white); five columns of 2.6 inches at 110 dpi.
    with Image.open(demo_dir / demo.RENDER_FILE) as image:
        assert image.width > 1300 and image.height > 550
    assert white_fraction(demo_dir / demo.RENDER_FILE) < 0.45
    report = json.loads((demo_dir / demo.METRICS_FILE).read_text())
    clean, f = load_mesh(demo_dir / "clean.obj")
    assert report["mesh"]["n_vertex"] == len(clean) and report["mesh"]["n_face"] == len(f)
    assert report["mesh"]["category"] == demo.DEMO_CATEGORY
    # The stored metrics are those of the written meshes.
    for name, filename in demo.MESH_FILES.items():
        if name == "clean":
            continue
        v, f2 = load_mesh(demo_dir / filename)
        np.testing.assert_array_equal(f, f2)
        expected = mesh_metrics(v, clean, f)
        for key in ("vertex", "vertex_per_coord", "normal_deg", "chamfer"):
            assert report["metrics"][name][key] == pytest.approx(expected[key], rel=1e-9)
    # The two classic filters clean up a 0.2-edge-length Gaussian noise on this part.
    m = report["metrics"]
    assert m["taubin"]["normal_deg"] < m["noisy"]["normal_deg"]
    assert m[demo.FEATURE_BASELINE]["normal_deg"] < m["noisy"]["normal_deg"]


def test_demo_noise_is_what_it_says(demo_dir):
    from dmd_jax import demo
    from dmd_jax.noise import vertex_normals_np

    clean, f = load_mesh(demo_dir / "clean.obj")
    noisy, _ = load_mesh(demo_dir / "noisy.obj")
    # The benchmark protocol: one N(0, σ²) draw per vertex along its vertex normal. About
    # 5,200 draws: their RMS is within 3 % of σ (3 standard errors).
    expected = demo.NOISE_LEVEL * mean_edge_length(clean, f)
    d = noisy - clean
    assert np.sqrt(np.mean(np.sum(d**2, axis=1))) == pytest.approx(expected, rel=0.03)
    along = np.sum(d * vertex_normals_np(clean, f), axis=1)
    np.testing.assert_allclose(np.abs(along), np.linalg.norm(d, axis=1), atol=1e-12)
    assert abs(np.mean(along)) < 0.05 * expected
    # The clean mesh is the procedural shape, in its canonical frame.
    extent = clean.max(0) - clean.min(0)
    assert extent.max() == pytest.approx(1.0)
    np.testing.assert_allclose(clean.max(0) + clean.min(0), 0.0, atol=1e-12)


def test_demo_refuses_existing_outputs(demo_dir, capsys, weights):
    before = (demo_dir / "clean.obj").stat().st_mtime_ns
    code, _, err = run(capsys, "demo", "--out", demo_dir, "--weights", weights)
    assert_one_line_error(code, err, "already exist", "--overwrite")
    assert (demo_dir / "clean.obj").stat().st_mtime_ns == before


def test_demo_uses_the_bundled_weights_by_default(monkeypatch, tmp_path, capsys, weights):
    from dmd_jax import demo

    monkeypatch.setattr(checkpoints, "pretrained_path", lambda: tmp_path / "absent.msgpack")
    code, _, err = run(capsys, "demo", "--out", tmp_path / "demo")
    assert_one_line_error(code, err, "bundled weights are missing", "--weights")
    assert not (tmp_path / "demo").exists()
    monkeypatch.setattr(checkpoints, "pretrained_path", lambda: weights)
    assert demo.load_bundle(None).meta == {"note": "tiny"}


# ---------------------------------------------------------------- rough edges (issue 16)


def test_point_cloud_ply_is_named_a_point_cloud(capsys, tmp_path):
    cloud = tmp_path / "scan.ply"
    points = np.random.default_rng(0).random((50, 3))
    cloud.write_text(
        "ply\nformat ascii 1.0\nelement vertex 50\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n" + "".join(f"{x} {y} {z}\n" for x, y, z in points)
    )
    code, _, err = run(capsys, "denoise", cloud, "-o", tmp_path / "o.ply")
    assert_one_line_error(code, err, "scan.ply", "point cloud", "50 vertices", "triangle mesh")
    assert "holds 0" not in err


def test_directory_as_input(capsys, tmp_path, files):
    # `denoise` takes folders (of meshes) since it has a folder mode: with -o it says so.
    code, _, err = run(capsys, "denoise", files, "-o", tmp_path / "o.obj")
    assert_one_line_error(code, err, "take --out DIR, not -o/--output")
    assert "unknown mesh format" not in err
    empty = tmp_path / "empty"
    empty.mkdir()
    code, _, err = run(capsys, "evaluate", "--gt", empty, "--mesh", files / "noisy.obj")
    assert_one_line_error(code, err, "is a directory")


def _quad_grid(n: int = 4) -> str:
    """An OBJ of an n × n grid of quads (a flat open patch)."""
    lines = [f"v {i} {j} {0.1 * ((i * j) % 3)}" for j in range(n + 1) for i in range(n + 1)]
    for j in range(n):
        for i in range(n):
            a = j * (n + 1) + i + 1
            lines.append(f"f {a} {a + 1} {a + n + 2} {a + n + 1}")
    return "\n".join(lines) + "\n"


def test_quad_triangulation_is_one_note(capsys, tmp_path):
    quads = tmp_path / "quads.obj"
    quads.write_text(_quad_grid())
    code, out, err = run(capsys, "add-noise", quads, "-o", tmp_path / "n.obj", "--level", "0.01")
    assert code == 0 and "added" in out
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("note: ") and "triangulated 16 polygon faces" in lines[0]
    assert "Warning" not in err and "warn(" not in err


def test_zero_area_faces_are_reported(capsys, tmp_path, files):
    v, f = icosphere(1)
    # One extra face on three collinear vertices: zero area, no repeated index.
    v = np.concatenate([v, [[0.0, 0.0, 2.0], [0.0, 0.0, 3.0], [0.0, 0.0, 4.0]]])
    f = np.concatenate([f, [[len(v) - 3, len(v) - 2, len(v) - 1]]])
    save_mesh(tmp_path / "flat.obj", v, f)
    code, _, err = run(
        capsys, "evaluate", "--gt", tmp_path / "flat.obj", "--mesh", tmp_path / "flat.obj"
    )
    assert code == 0
    notes = [line for line in err.splitlines() if "zero area" in line]
    assert len(notes) == 2  # once per file read (the same file, twice)
    assert notes[0].startswith("note: ") and f"1 of {len(f)} faces" in notes[0]
    code, _, err = run(
        capsys, "evaluate", "--gt", files / "clean.obj", "--mesh", files / "noisy.obj"
    )
    assert code == 0 and err == ""


def test_method_help_and_error_list_every_method(capsys, files, tmp_path):
    from dmd_jax.cli import METHODS, build_parser

    assert set(METHODS) == {"dmd", *baselines.REGISTRY, *baselines.LEARNED}
    assert len(METHODS) == len(set(METHODS))
    help_text = _subparser(build_parser(), "denoise").format_help()
    for name in METHODS:
        assert name in help_text
    code, _, err = run(
        capsys, "denoise", files / "noisy.obj", "-o", tmp_path / "x.obj", "--method", "magic"
    )
    assert_one_line_error(code, err, "magic", ", ".join(METHODS))


def test_weights_with_a_classic_method_is_an_error(capsys, files, tmp_path, weights):
    code, _, err = run(
        capsys,
        "denoise",
        files / "noisy.obj",
        "-o",
        tmp_path / "x.obj",
        "--method",
        "bnf",
        "--weights",
        weights,
    )
    assert_one_line_error(code, err, "--weights", "'bnf'", "no weights")
    assert not (tmp_path / "x.obj").exists()


def _subparser(parser, name):
    import argparse

    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return action.choices[name]


def test_help_shows_defaults_and_an_example_per_subcommand():
    import argparse

    from dmd_jax.cli import EXAMPLES, build_parser

    parser = build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert set(action.choices) == set(EXAMPLES)
    for name, sub in action.choices.items():
        text = " ".join(sub.format_help().split())
        assert "example: dmd-jax " + name in text, name
        for opt in sub._actions:
            if isinstance(opt, argparse._HelpAction):
                continue
            assert opt.help, f"{name} {opt.option_strings or opt.dest} has no help"
            if opt.option_strings and opt.default not in (None, False):
                shown = " ".join(sub._get_formatter()._expand_help(opt).split())
                assert "default" in shown, f"{name} {opt.option_strings}: {shown}"
    denoise = " ".join(_subparser(parser, "denoise").format_help().split())
    assert "(default: dmd)" in denoise and "(default: 1 for a classic filter;" in denoise
    noise = " ".join(_subparser(parser, "add-noise").format_help().split())
    assert "(default: gaussian)" in noise and "σ for gaussian" in noise


def test_make_dataset_empty_test_inter_holds_out_nothing(capsys, tmp_path):
    out = tmp_path / "data"
    code, stdout, err = run(
        capsys,
        "make-dataset",
        "--out",
        out,
        "--per-category",
        "1",
        "--categories",
        "torus,superquadric",
        "--test-inter",
        "",
        "--workers",
        "1",
        "--min-vertices",
        "300",
        "--max-vertices",
        "800",
        "--no-progress",
    )
    assert code == 0, err
    assert "test_inter 0 (none)" in stdout
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["test_inter"] == []


def test_readme_commands_write_distinct_outputs():
    """Consecutive commands of a README code block never write the same output name."""
    import re
    import shlex

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    for block in re.findall(r"```bash\n(.*?)```", readme, flags=re.S):
        text = block.replace("\\\n", " ")
        outputs = []
        for line in text.splitlines():
            line = line.split("#")[0].strip()
            if not line.startswith("dmd-jax "):
                continue
            words = shlex.split(line)
            for flag in ("-o", "--output", "--out"):
                if flag in words and words[1] not in ("train",):
                    outputs.append(words[words.index(flag) + 1])
        assert len(outputs) == len(set(outputs)), f"repeated outputs in:\n{block}"


def test_export_weights_says_which_step(capsys, tmp_path):
    import jax.numpy as jnp

    from dmd_jax.checkpoints import checkpoint_managers, save_checkpoint
    from dmd_jax.train import TrainState
    from dmd_jax.train import split_params as split

    latest, _ = checkpoint_managers(tmp_path / "run", 1)
    state = TrainState(jnp.asarray(7, jnp.int32), split(tiny_params()), {"fe": {}, "rest": {}})
    save_checkpoint(latest, state, TINY_CONFIG)
    ckpt = tmp_path / "run" / "checkpoints" / "latest"
    code, out, err = run(capsys, "export-weights", ckpt, "-o", tmp_path / "w.msgpack")
    assert code == 0, err
    assert "step 7" in out and str(ckpt) in out and "preset test" in out
    assert checkpoints.load_weights(tmp_path / "w.msgpack").meta["step"] == 7
    assert checkpoints.load_weights(tmp_path / "w.msgpack").policy == DenoisePolicy()
    args = ("export-weights", ckpt, "-o", tmp_path / "t.msgpack", "--pass-tolerance", "0.25")
    code, out, err = run(capsys, *args)
    assert code == 0, err
    # A tolerance on a one-pass policy gets the pass cap such weights always had.
    policy = checkpoints.load_weights(tmp_path / "t.msgpack").policy
    assert (policy.pass_tolerance, policy.max_passes) == (0.25, 8)
    # A weights file in: the same params and provenance, a new pre-smoothing rule.
    args = ("export-weights", tmp_path / "t.msgpack", "-o", tmp_path / "p.msgpack")
    code, out, err = run(capsys, *args, "--presmooth", "30", "4")
    assert code == 0, err
    before, after = (checkpoints.load_weights(tmp_path / n) for n in ("t.msgpack", "p.msgpack"))
    rule = after.policy
    assert (rule.presmooth_start, rule.presmooth_per_step, rule.pass_tolerance) == (30, 4, 0.25)
    assert after.config == before.config
    code, out, err = run(capsys, "info", "--weights", tmp_path / "p.msgpack")
    assert code == 0 and "pass_tolerance 0.25" in out and "presmooth_start 30.0" in out
    args = ("export-weights", tmp_path / "p.msgpack", "-o", tmp_path / "r.msgpack")
    code, _, err = run(capsys, *args, "--max-passes", "3", "--relax-steps", "2")
    assert code == 0, err
    rule = checkpoints.load_weights(tmp_path / "r.msgpack").policy
    assert (rule.max_passes, rule.relax_steps, rule.pass_tolerance) == (3, 2, 0.25)
    code, _, err = run(capsys, *args, "--overwrite", "--max-passes", "1000")
    assert code != 0 and "--max-passes must be from 1 to 64, got 1000" in err
    assert after.meta["step"] == 7 and after.meta["exported_from"] == str(tmp_path / "t.msgpack")
    for a, b in zip(jax.tree.leaves(before.params), jax.tree.leaves(after.params), strict=True):
        np.testing.assert_array_equal(a, b)
    # `info` prints the bundled policy's rules in one line; --presmooth edits the rule.
    code, out, err = run(capsys, "info", "--weights", "bundled")
    assert code == 0, err
    (line,) = [x for x in out.splitlines() if x.strip().startswith("policy:")]
    bundled = checkpoints.load_weights(checkpoints.pretrained_path()).policy
    assert bundled.describe() in line and len(line) < 1000
    args = ("export-weights", checkpoints.pretrained_path(), "-o", tmp_path / "b.msgpack")
    code, _, err = run(capsys, *args, "--presmooth", "30", "4")
    assert code == 0, err
    policy = checkpoints.load_weights(tmp_path / "b.msgpack").policy
    assert policy.presmooth_start == 30 and policy.presmooth_per_step == 4
    # --policy-from: a fine-tune's checkpoint with the policy of the weights it started
    # from (here the bundled rules), its own params and config.
    args = ("export-weights", ckpt, "-o", tmp_path / "f.msgpack", "--policy-from", "bundled")
    code, _, err = run(capsys, *args)
    assert code != 0 and "bundled" in err  # a path, not the `--weights` alias
    args = ("export-weights", ckpt, "-o", tmp_path / "f.msgpack")
    code, _, err = run(capsys, *args, "--policy-from", checkpoints.pretrained_path())
    assert code == 0, err
    tuned = checkpoints.load_weights(tmp_path / "f.msgpack")
    # The rules, not a controller trained for the donor's network (nor its switch).
    assert tuned.policy == bundled.replace(controller=False) and tuned.config == TINY_CONFIG
    assert tuned.controller is None
    assert tuned.meta["policy_from"] == str(checkpoints.pretrained_path())
    code, _, err = run(capsys, *args, "--overwrite", "--policy-from", tmp_path / "r.msgpack")
    assert code == 0, err
    assert checkpoints.load_weights(tmp_path / "f.msgpack").policy.max_passes == 3


@pytest.mark.slow  # measured 18-26 s on 2 idle cores; `make test-slow` runs it
def test_train_init_from_weights_file_or_checkpoint(tmp_path):
    """`train --init-from` (`train.init_params_from`) takes a weights file or a checkpoint;
    settings without parameters (vertex iterations, pass tolerance) may differ, parameter
    shapes may not."""
    import jax.numpy as jnp

    from dmd_jax.checkpoints import checkpoint_managers, save_checkpoint, save_weights
    from dmd_jax.train import TrainState, init_params_from
    from dmd_jax.train import split_params as split

    params = tiny_params()
    source = TINY_CONFIG
    save_weights(tmp_path / "w.msgpack", params, source, policy=DenoisePolicy(pass_tolerance=0.2))
    latest, _ = checkpoint_managers(tmp_path / "run", 1)
    save_checkpoint(latest, TrainState(jnp.asarray(3), split(params), {}), source)
    run_cfg = TINY_CONFIG.with_edits({"model": {"vertex_iterations": 20}})
    for path in (tmp_path / "w.msgpack", tmp_path / "run" / "checkpoints" / "latest"):
        got = init_params_from(path, run_cfg)
        for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(got), strict=True):
            np.testing.assert_array_equal(a, b)
    wider = TINY_CONFIG.with_edits({"model": {"width": TINY_CONFIG.model.width * 2}})
    with pytest.raises(ValueError, match="do not fit.*width"):
        init_params_from(tmp_path / "w.msgpack", wider)
    with pytest.raises(FileNotFoundError):
        init_params_from(tmp_path / "missing.msgpack", run_cfg)
    # A trained normal-first head grows the zero-initialised consistency input.
    from dmd_jax.model import init_params

    normal = preset("test")
    trained = init_params(normal.model, jax.random.PRNGKey(1))
    save_weights(tmp_path / "n.msgpack", trained, normal)
    grown = init_params_from(
        tmp_path / "n.msgpack", normal.with_edits({"model": {"head_consistency": True}})
    )
    old = {jax.tree_util.keystr(k): v for k, v in jax.tree_util.tree_flatten_with_path(trained)[0]}
    new = {jax.tree_util.keystr(k): v for k, v in jax.tree_util.tree_flatten_with_path(grown)[0]}
    assert set(old) < set(new)
    for key, value in old.items():
        np.testing.assert_array_equal(value, new[key])


def test_add_noise_and_denoise_with_at_the_root(files):
    import dmd_jax

    clean, f = load_mesh(files / "clean.obj")
    noisy = dmd_jax.add_noise(3, clean, f, "gaussian", 0.2, units="edge")
    assert isinstance(noisy, np.ndarray) and noisy.dtype == np.float64
    # The same noise as `dmd-jax add-noise --seed 3` (float32 draws, float64 sums).
    np.testing.assert_allclose(noisy, load_mesh(files / "noisy.obj")[0], rtol=0, atol=1e-6)
    noisy32 = dmd_jax.add_noise(3, clean.astype(np.float32), f, "gaussian", 0.2, units="edge")
    assert noisy32.dtype == np.float32
    np.testing.assert_allclose(noisy32, noisy, atol=1e-6)
    with pytest.raises(ValueError, match="seed"):
        dmd_jax.add_noise(True, clean, f, "gaussian", 0.2)
    with pytest.raises(ValueError, match="level"):
        dmd_jax.add_noise(0, clean, f, "gaussian", -1.0)
    # One call for every method; the same result as each method's own entry point.
    np.testing.assert_allclose(
        dmd_jax.denoise_with("taubin", noisy, f), baselines.run_baseline("taubin", noisy, f)
    )
    assert dmd_jax.denoise_with("bnf", noisy32, f).dtype == np.float32
    with pytest.raises(ValueError, match="dmd, laplacian"):
        dmd_jax.denoise_with("magic", noisy, f)
    with pytest.raises(ValueError, match="no weights"):
        dmd_jax.denoise_with("bnf", noisy, f, weights="w.msgpack")


def test_render_flags_png_and_html(files, capsys, tmp_path):
    from PIL import Image

    from dmd_jax.render import white_fraction

    common = [files / "noisy.obj", files / "dmd.obj", "--gt", files / "clean.obj"]
    png = tmp_path / "cmp.png"
    code, _, err = run(
        capsys,
        "render",
        *common,
        "-o",
        png,
        "--elev",
        "35",
        "--azim",
        "-30",
        "--up",
        "z",
        "--panel-size",
        "2",
        "--range",
        "0",
        "30",
    )
    assert code == 0, err
    with Image.open(png) as image:
        # Three columns (noisy, dmd, the clean --gt), the longer side of a panel 2 inches
        # at 110 dpi (a sphere: about square), and three rows.
        assert 3 * 200 < image.width <= 3 * 220 and image.height > 3 * 200
    assert white_fraction(png) < 0.5
    small = tmp_path / "small.png"
    assert run(capsys, "render", *common, "-o", small, "--no-zoom", "--panel-size", "1")[0] == 0
    with Image.open(small) as image:
        assert 300 < image.width <= 330 and image.height < 3 * 110  # two rows: no zoom
    page = tmp_path / "cmp.html"
    code, out, _ = run(capsys, "render", *common, "-o", page, "--titles", "noisy,DMD-Net")
    assert code == 0 and str(page) in out
    html = page.read_text(encoding="utf-8")
    assert "DMD-Net" in html and "clean" in html and '<script src="http' not in html
    code, _, err = run(capsys, "render", *common, "-o", tmp_path / "cmp.jpg")
    assert_one_line_error(code, err, ".png", ".html")
    code, _, err = run(capsys, "render", *common, "-o", tmp_path / "r.png", "--range", "5", "1")
    assert_one_line_error(code, err, "--range")
    code, _, err = run(capsys, "render", *common, "-o", tmp_path / "t.png", "--titles", "a,b,c,d")
    assert_one_line_error(code, err, "4 titles for 3 panels")

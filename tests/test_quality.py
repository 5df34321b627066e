"""The quality scripts (`benchmarks/quality/`) on one small mesh, and the rules of
`benchmarks/`: no script imports another script, every report states its provenance."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from conftest import REPO, shared_mesh_path
from test_inference import TINY_CONFIG, tiny_params

from benchmarks.common import BUNDLED, file_sha256, provenance
from dmd_jax import checkpoints, inference, protocol
from dmd_jax.io import load_mesh
from dmd_jax.metrics import mesh_metrics, metrics_legend

BENCHMARKS = REPO / "benchmarks"


@pytest.fixture(scope="module")
def weights(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("weights") / "tiny.msgpack"
    return checkpoints.save_weights(path, tiny_params(), TINY_CONFIG, {"note": "tiny"})


def test_sota_lite_on_one_mesh(tmp_path, weights):
    from benchmarks.quality import sota_lite

    mesh = shared_mesh_path("decimated-knight.off")
    folder = tmp_path / "meshes"
    folder.mkdir()
    (folder / mesh.name).symlink_to(mesh)
    code = sota_lite.main(
        [
            "--meshes",
            str(folder),
            "--weights",
            str(weights),
            "--conditions",
            "0.2",
            "impulse:0.3",
            "--methods",
            "meshlab_taubin",
            "bnf",
            "dmd",
            "dmd_x2",
            "--no-val",
            "--sets",
            "shared",
            "--name",
            "t",
            "--out-dir",
            str(tmp_path),
        ]
    )
    assert code == 0
    import csv

    with open(tmp_path / "t.csv") as fh:
        rows = list(csv.DictReader(fh))
    methods = ["noisy", "meshlab_taubin", "bnf", "dmd", "dmd_x2"]
    assert [r["method"] for r in rows] == methods * 2
    assert [r["noise"] for r in rows] == ["gaussian"] * 5 + ["impulse"] * 5
    assert {r["set"] for r in rows} == {"shared"}
    impulse = protocol.NoiseCondition("impulse", 0.3)
    assert int(rows[5]["seed"]) == protocol.condition_seed(mesh.name, impulse)
    clean, f = load_mesh(mesh)
    noisy = protocol.benchmark_noise(clean, f, 0.2, protocol.noise_seed(mesh.name, 0.2))
    expected = mesh_metrics(noisy, clean, f)["normal_deg"]
    assert float(rows[0]["normal_deg"]) == pytest.approx(expected, rel=1e-12)
    dmd = inference.denoise(noisy, f, weights)
    assert float(rows[3]["normal_deg"]) == pytest.approx(
        mesh_metrics(dmd, clean, f)["normal_deg"], rel=1e-9
    )
    # The crease / flat split against a direct computation.
    from dmd_jax import comparison
    from dmd_jax.metrics import face_normal_errors_deg

    errors = face_normal_errors_deg(dmd, clean, f, undefined=float("nan"))
    crease, flat = comparison.region_errors(errors, comparison.crease_faces(clean, f))
    assert float(rows[3]["normal_crease_deg"]) == pytest.approx(crease, rel=1e-9)
    assert float(rows[3]["normal_flat_deg"]) == pytest.approx(flat, rel=1e-9)
    assert rows[3]["cad"] == str(comparison.is_cad(clean, f))
    report = (tmp_path / "t.md").read_text()
    assert "## Means over meshes" in report and "decimated-knight.off" in report
    assert "## Per shape: DMD-Net against the best other library denoiser" in report
    ratio = float(rows[3]["normal_deg"]) / float(rows[2]["normal_deg"])  # against BNF
    shapes = report.split("## Per shape")[1].split("\n## ")[0]
    shape_row = next(line for line in shapes.splitlines() if line.startswith("| shared | 0.2 |"))
    assert f"| {ratio:.3f} |" in shape_row
    assert "| shared | impulse 0.3 |" in report
    assert "DMD-Net margin" in report and "Median run time" in report
    # --reuse recomputes DMD-Net only: the classic rows come back identical.
    assert (
        sota_lite.main(
            ["--meshes", str(folder), "--weights", str(weights), "--conditions", "0.2"]
            + ["--methods", "bnf", "dmd", "--no-val", "--sets", "shared", "--reuse"]
            + ["--name", "t", "--out-dir", str(tmp_path)]
        )
        == 0
    )
    with open(tmp_path / "t.csv") as fh:
        again = {r["method"]: r for r in csv.DictReader(fh)}
    assert again["bnf"] == rows[2]
    # The three metrics in the vocabulary of `dmd-jax evaluate`, with its legend.
    assert "| method | vertex (×1e-4) | normal (°) | chamfer (×1e-4) |" in report
    assert metrics_legend() in report
    dmd_row = next(line for line in report.splitlines() if line.startswith("| DMD-Net |"))
    both = (float(rows[3]["normal_deg"]) + float(rows[8]["normal_deg"])) / 2  # over conditions
    assert float(dmd_row.split("|")[3]) == pytest.approx(both, abs=0.01)
    assert str(weights) in report and "jax" in report
    # The provenance line under the title: commit and the weights file's SHA-256.
    assert f"with weights `{weights.name}` (SHA-256 `{file_sha256(weights)}`)" in report


def test_sota_lite_errors(tmp_path, capsys):
    from benchmarks.quality import sota_lite

    assert sota_lite.main(["--meshes", str(tmp_path / "none")]) == 2
    assert "no mesh folder" in capsys.readouterr().err
    assert sota_lite.main(["--meshes", str(tmp_path), "--skip", "x.obj"]) == 2
    assert "x.obj" in capsys.readouterr().err


def test_no_harm_on_one_mesh(tmp_path, weights):
    from benchmarks.quality import no_harm

    mesh = shared_mesh_path("decimated-knight.off")
    folder = tmp_path / "meshes"
    folder.mkdir()
    (folder / mesh.name).symlink_to(mesh)
    out = tmp_path / "no_harm.md"
    argv = ["--meshes", str(folder), "--weights", str(weights), "--out", str(out)]
    assert no_harm.main([*argv, "--sets", "shared"]) == 0
    report = out.read_text()
    assert "decimated-knight.off" in report and "dmd normal change" in report
    assert f"(SHA-256 `{file_sha256(weights)}`)" in report


def test_provenance_names_commit_and_weights(tmp_path, weights):
    line = provenance(weights)
    assert line.startswith("Made at commit `") and file_sha256(weights) in line
    assert len(file_sha256(weights)) == 12
    assert "no trained weights" in provenance(None)
    assert "(missing)" in provenance(tmp_path / "none.msgpack")
    assert "a checkpoint directory" in provenance(tmp_path)
    if checkpoints.pretrained_path().is_file():
        assert "bundled `dmd_small.msgpack`" in provenance(BUNDLED)


def _script_imports(path: Path) -> list[str]:
    """The modules a file imports (absolute names; `common` for a bare sibling import)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.append(node.module)
    return out


# The library modules of `benchmarks/`: imported by scripts, never run.
BENCHMARK_LIBRARIES = {
    "common.py": "benchmarks.common",
    "sota_tables.py": "benchmarks.quality.sota_tables",  # the sota-lite report's tables
}


def test_no_benchmark_script_imports_another_script():
    """Scripts share code through the library modules (`benchmarks.common`, and the
    sota-lite report's tables) and the package, never through each other, and import
    them in one style."""
    scripts = sorted(
        p
        for p in BENCHMARKS.rglob("*.py")
        if p.name not in ("__init__.py", *BENCHMARK_LIBRARIES) and "results" not in p.parts
    )
    assert len(scripts) >= 8
    stems = {p.stem for p in scripts}
    libraries = {name.removesuffix(".py") for name in BENCHMARK_LIBRARIES}
    for path in scripts:
        for module in _script_imports(path):
            parts = module.split(".")
            if parts[0] == "benchmarks":
                assert module in BENCHMARK_LIBRARIES.values(), (path.name, module)
            else:
                assert parts[0] not in stems | libraries, (path.name, module)
        assert "__main__" in path.read_text(), f"{path.name} is not a script"


def test_every_report_writer_states_its_provenance():
    """Every script that writes a report goes through `write_report` (whose header is
    `provenance`) or, for Table II, calls `provenance` itself."""
    for path in sorted(BENCHMARKS.rglob("*.py")):
        text = path.read_text()
        if path.name in ("common.py", "__init__.py") or ".md" not in text:
            continue
        assert "write_report(" in text or "provenance(" in text, path.name


def test_sota_lite_per_shape_and_region_tables_from_rows():
    from benchmarks.quality import sota_lite

    def row(mesh, method, normal, crease, flat, cad=True, noise="gaussian", level=0.2):
        return ["shared", mesh, 10, 20, level, 1, method, normal, 0.0, 0.0, 0.1, noise, cad] + [
            crease,
            flat,
        ]

    rows = [
        row("a.obj", "bnf", 2.0, 6.0, 1.0),
        row("a.obj", "cnr", 4.0, 5.0, 3.0),
        row("a.obj", "dmd", 1.0, 5.5, 0.5),
        row("b.obj", "bnf", 2.0, 8.0, 1.0, cad=False),
        row("b.obj", "cnr", 1.0, 2.0, 1.0, cad=False),
        row("b.obj", "dmd", 2.0, 1.0, 1.0, cad=False),
    ]
    shapes = sota_lite.per_shape_table(rows)
    # Ratios 0.5 (a, against BNF) and 2.0 (b, against CNR): geometric mean 1.
    assert "| shared | 0.2 | 2 | 1.000 | 1 (50 %) | 1 | 2.00 (b.obj) |" in shapes
    regions = sota_lite.region_table(rows)
    # Only a.obj is CAD: crease 5.5 against CNR's 5.0, flat 0.5 against BNF's 1.0.
    assert "| shared | 0.2 | 1 | 5.50 | 5.00 (CNR) | +0.50 | 0.50 | 1.00 (BNF) | -0.50 |" in regions
    assert "CAD meshes: `shared`: a.obj." in regions


def test_design_bounds_reads_each_designs_best_off_the_grid(tmp_path, monkeypatch):
    """Two meshes under one condition: each design's bound is the best of the options it
    may choose, over the best other method, as the report's geometric mean / worst."""
    import csv

    from benchmarks.quality import oracle_val

    labels = [o.label for o in oracle_val.grid_options()]
    grid = tmp_path / "grid.csv"
    sota = tmp_path / "sota.csv"
    best = {
        "a.ply": ("p8_jacobi_2", 2.0, "p0_solve_3", 4.0),
        "b.ply": ("p0_jacobi_1", 3.0, "p0_solve_1", 5.0),
    }
    with open(grid, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=oracle_val.header())
        w.writeheader()
        for mesh, (anywhere, e_any, solve, e_solve) in best.items():
            errs = {k: 10.0 for k in labels}
            errs[anywhere], errs[solve] = e_any, e_solve
            errs["p0_jacobi_4"] = min(errs["p0_jacobi_4"], 6.0)
            # As `oracle_val.py --controller-weights none` writes a row: no controller pick.
            row = {"set": "val", "mesh": mesh, "noise": "gaussian", "level": "0.2", **errs}
            row.update(noisy_deg=20.0, held_vertices=0, controller_option="")
            row.update(oracle_option=anywhere, oracle_deg=e_any)
            w.writerow(row)
    with open(sota, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["set", "mesh", "noise", "level", "method", "normal_deg"])
        w.writeheader()
        for mesh in best:
            for method, err in (("dmd", 8.0), ("bilateral", 4.0), ("noisy", 20.0)):
                w.writerow(
                    {
                        "set": "val",
                        "mesh": mesh,
                        "noise": "gaussian",
                        "level": "0.2",
                        "method": method,
                        "normal_deg": err,
                    }
                )
    monkeypatch.setattr(oracle_val, "SOTA_CSVS", (sota,))
    text = oracle_val.design_bounds([(None, grid, ())], tmp_path / "bounds.md").read_text()
    row = next(line for line in text.splitlines() if line.startswith("| 0.2 "))
    cells = [c.strip() for c in row.strip("|").split("|")]
    # default 8/4 both; oracle 2/4 and 3/4; stop (no pre-smoothing) 4/4 (a: solve 3) and
    # 3/4 (b: Jacobi 1); Jacobi only 6/4 and 3/4; solve only 4/4 and 5/4.
    assert cells[3] == "2.000 / 2.00"
    assert cells[4] == f"{(0.5 * 0.75) ** 0.5:.3f} / 0.75 ✓"
    assert cells[5] == f"{0.75**0.5:.3f} / 1.00 ✓"
    assert cells[6] == f"{(1.5 * 0.75) ** 0.5:.3f} / 1.50"
    assert cells[7] == f"{1.25**0.5:.3f} / 1.25"
    assert "the grid oracle (all 68 options): 1 of 1" in text


def test_oracle_val_writes_the_committed_report_only_for_its_own_grid(tmp_path, capsys):
    """Another --csv writes no report unless --report names one (scoring another grid
    or controller must not rewrite `controller_oracle_val.md`)."""
    from benchmarks.quality import oracle_val

    before = oracle_val.DEFAULT_REPORT.read_bytes()
    grid = tmp_path / "grid.csv"
    grid.write_text(",".join(oracle_val.header()) + "\n")
    assert oracle_val.main(["--report-only", "--csv", str(grid)]) == 0
    assert "no report" in capsys.readouterr().out
    assert oracle_val.DEFAULT_REPORT.read_bytes() == before
    # Named, it is written (here: an error, the grid holds no case).
    assert (
        oracle_val.main(["--report-only", "--csv", str(grid), "--report", str(tmp_path / "r.md")])
        == 2
    )
    assert "no case to report" in capsys.readouterr().err

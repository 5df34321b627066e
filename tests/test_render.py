"""Static pictures (`dmd_jax.render`), the HTML viewer (`dmd_jax.viewer`) and the metrics
vocabulary (`dmd_jax.metrics.metrics_table`).

The browser test loads a page in headless Chromium (Debian's `chromium` package) and
checks the screenshot is not blank; it is skipped where no Chromium is installed.
"""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest
from conftest import icosphere

from dmd_jax.metrics import (
    DEFAULT_METRICS,
    face_normal_errors_deg,
    mesh_metrics,
    metric_header,
    metrics_legend,
    metrics_table,
)
from dmd_jax.render import (
    dihedral_angles,
    guess_up_axis,
    nice_range,
    render_meshes,
    resolve_up,
    sharpest_face,
    white_fraction,
)


def box() -> tuple[np.ndarray, np.ndarray]:
    """A closed box 1 × 0.8 × 0.3 (Z up), each side subdivided: sharp 90° edges."""
    import trimesh

    mesh = trimesh.creation.box(extents=(1.0, 0.8, 0.3))
    for _ in range(2):
        mesh = mesh.subdivide()
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int32)


@pytest.fixture(scope="module")
def noisy_box():
    v, f = box()
    rng = np.random.default_rng(0)
    noisy = v + 0.01 * rng.standard_normal(v.shape)
    return v, noisy, f


def test_nice_range_resolves_the_best_panel():
    good = np.linspace(0, 10, 101)  # p95 = 9.5 -> 10
    bad = np.linspace(0, 60, 101)
    assert nice_range([good, bad]) == (0.0, 10.0)
    assert nice_range([np.full(10, 0.3)]) == (0.0, 0.5)
    assert nice_range([np.array([-3.0, 1.0, 2.0])]) == (-5.0, 5.0)  # p95 of |x| = 2.9
    assert nice_range([np.zeros(5)]) == (0.0, 1.0)


def test_dihedral_angles_of_a_box_are_90_on_edges():
    v, f = box()
    d = dihedral_angles(v, f)
    assert d.max() == pytest.approx(90.0, abs=1e-6)
    assert np.isclose(d, 0.0, atol=1e-6).sum() > 0  # interior faces of a side are flat


def test_sharpest_face_lies_on_a_sharp_edge(noisy_box):
    v, _, f = noisy_box
    face = sharpest_face(v, f)
    assert dihedral_angles(v, f)[face] == pytest.approx(90.0, abs=1e-6)


def test_up_axis_guess_and_vote():
    from conftest import shared_mesh_path

    from dmd_jax.data import generate_shape
    from dmd_jax.io import load_mesh

    v, f = box()
    assert guess_up_axis(v, f) == "z"  # a clear flat base under Z
    # The same box turned Y-up (its 0.3 side along Y): no clear base under Z, so Y.
    y_up = np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1)
    assert guess_up_axis(y_up, f) == "y"
    # A generated nut stands on Z; the Stanford bunny (a scan) is Y-up.
    assert guess_up_axis(*generate_shape("fastener", 2024, 2)) == "z"
    assert guess_up_axis(*load_mesh(shared_mesh_path("bunny.off"))) == "y"
    assert resolve_up("auto", [(y_up, f), (y_up, f), (v, f)]) == "y"
    assert resolve_up("z", [(y_up, f)]) == "z"
    with pytest.raises(ValueError, match="up must be"):
        resolve_up("x", [(v, f)])


def test_render_rows_fill_the_figure(noisy_box, tmp_path):
    from PIL import Image

    v, noisy, f = noisy_box
    values = [face_normal_errors_deg(noisy, v, f), None]
    png = render_meshes(
        [(noisy, f), (v, f)],
        tmp_path / "cmp.png",
        titles=["noisy", "clean"],
        face_values=values,
        shaded_row=True,
        crop_face=sharpest_face(v, f),
        panel_size=2.0,
    )
    with Image.open(png) as image:
        width, height = image.size
    # Two columns of 2 inches at 110 dpi; three rows (shaded, zoom, error) and a title.
    assert width == 440
    assert height > 2 * 0.6 * 220
    # The old layout was ~70 % white; panels now fill the figure.
    assert white_fraction(png) < 0.45


def test_render_y_up_model_is_seen_from_above(tmp_path):
    """A Y-up box rendered with up='y' looks like the Z-up box with up='z'."""
    from PIL import Image

    v, f = box()
    y_up = np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1)
    a = render_meshes([(v, f)], tmp_path / "z.png", up="z", panel_size=1.5)
    b = render_meshes([(y_up, f)], tmp_path / "y.png", up="y", panel_size=1.5)
    c = render_meshes([(y_up, f)], tmp_path / "wrong.png", up="z", panel_size=1.5)
    with Image.open(a) as ia, Image.open(b) as ib, Image.open(c) as ic:
        pa, pb, pc = (np.asarray(i.convert("L"), np.float64) for i in (ia, ib, ic))
    assert pa.shape == pb.shape
    assert np.mean(np.abs(pa - pb)) < 1.0
    assert pa.shape != pc.shape or np.mean(np.abs(pa - pc)) > 5.0


def test_render_checks_its_inputs(noisy_box, tmp_path):
    v, _, f = noisy_box
    with pytest.raises(ValueError, match="one value per face"):
        render_meshes([(v, f)], tmp_path / "a.png", face_values=[np.zeros(3)])
    with pytest.raises(ValueError, match="low < high"):
        render_meshes(
            [(v, f)], tmp_path / "a.png", face_values=[np.zeros(len(f))], value_range=(1, 1)
        )
    with pytest.raises(ValueError, match="crop_face"):
        render_meshes([(v, f)], tmp_path / "a.png", crop_face=len(f))


def test_comparison_html_is_self_contained(noisy_box, tmp_path):
    from dmd_jax.viewer import comparison_html

    v, noisy, f = noisy_box
    page = comparison_html(
        [(noisy, f), (v, f)],
        tmp_path / "cmp.html",
        titles=["noisy", "clean"],
        face_values=[face_normal_errors_deg(noisy, v, f), None],
    )
    html = page.read_text(encoding="utf-8")
    assert len(html) > 1_000_000  # plotly.js is inside
    assert '<script src="http' not in html and "<script src='http" not in html
    assert '"type":"mesh3d"' in html
    assert "plotly_relayout" in html  # the linked cameras
    with pytest.raises(FileExistsError):
        comparison_html([(v, f)], page)


def test_comparison_figure_panels_and_cameras(noisy_box):
    from dmd_jax.viewer import comparison_figure

    v, noisy, f = noisy_box
    fig = comparison_figure(
        [(noisy, f), (v, f), (v, f)],
        titles=["noisy", "denoised", "clean"],
        face_values=[face_normal_errors_deg(noisy, v, f), np.zeros(len(f)), None],
    )
    # One Mesh3d per panel and one invisible trace that carries the colour bar.
    assert [t.type for t in fig.data] == ["mesh3d", "mesh3d", "mesh3d", "scatter"]
    cameras = [fig.layout[name].camera.eye for name in ("scene", "scene2", "scene3")]
    assert cameras[0] == cameras[1] == cameras[2]
    assert fig.data[-1].marker.cmin == 0.0 and fig.data[-1].marker.cmax > 0


def chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.skipif(chromium() is None, reason="needs Chromium (apt-get install chromium)")
def test_comparison_html_renders_in_a_browser(noisy_box, tmp_path):
    """The page draws meshes in a real (headless) browser: the screenshot is not blank."""
    from PIL import Image

    from dmd_jax.viewer import comparison_html

    v, noisy, f = noisy_box
    page = comparison_html(
        [(noisy, f), (v, f)],
        tmp_path / "cmp.html",
        titles=["noisy", "clean"],
        face_values=[face_normal_errors_deg(noisy, v, f), None],
        panel_px=300,
    )
    shot = tmp_path / "shot.png"
    subprocess.run(
        [
            chromium(),
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--enable-unsafe-swiftshader",
            "--use-angle=swiftshader",
            "--hide-scrollbars",
            "--window-size=640,420",
            "--virtual-time-budget=10000",
            f"--screenshot={shot}",
            page.as_uri(),
        ],
        capture_output=True,
        timeout=120,
        check=True,
    )
    with Image.open(shot) as image:
        rgb = np.asarray(image.convert("RGB"), np.float64)
    # Not blank: a good share of the page is drawn, in several colours (grey shading
    # of the clean box, the error colours of the noisy one).
    drawn = np.any(rgb < 235, axis=-1)
    assert drawn.mean() > 0.08
    colours = {tuple(c) for c in (rgb[drawn] // 32).astype(int)}
    assert len(colours) > 10
    # Each panel holds a mesh: both halves of the plot area are drawn on.
    left, right = drawn[:, : rgb.shape[1] // 2], drawn[:, rgb.shape[1] // 2 :]
    assert left.mean() > 0.03 and right.mean() > 0.03


def test_metrics_table_has_one_vocabulary():
    v, f = icosphere(1)
    rng = np.random.default_rng(1)
    m = mesh_metrics(v + 0.01 * rng.standard_normal(v.shape), v, f)
    table = metrics_table({"noisy": m})
    header = table.splitlines()[0]
    assert [metric_header(s) for s in DEFAULT_METRICS] == [
        "vertex (×1e-4)",
        "normal (°)",
        "chamfer (×1e-4)",
    ]
    for s in DEFAULT_METRICS:
        assert metric_header(s) in header
    # The paper's per-coordinate vertex error is what the table shows.
    row = table.splitlines()[2].strip("|").split("|")
    assert float(row[1]) == pytest.approx(m["vertex_per_coord"] * 1e4, abs=1e-3)
    assert float(row[2]) == pytest.approx(m["normal_deg"], abs=0.01)
    assert table.rstrip().endswith(metrics_legend().rstrip())
    assert "per coordinate" in metrics_legend() and "canonical frame" in metrics_legend()
    text = metrics_table({"noisy": m}, style="text")
    assert text.splitlines()[0].split()[0] == "mesh" and "|" not in text
    with pytest.raises(ValueError, match="style"):
        metrics_table({"noisy": m}, style="latex")


@pytest.mark.skipif(chromium() is None, reason="needs Chromium (apt-get install chromium)")
def test_comparison_html_links_the_cameras_in_a_browser(noisy_box, tmp_path):
    """Turning one panel's camera turns the others (the page's plotly_relayout hook)."""
    import json
    import re

    from dmd_jax.viewer import comparison_html

    v, noisy, f = noisy_box
    page = comparison_html([(noisy, f), (v, f), (v, f)], tmp_path / "cmp.html", panel_px=200)
    probe = """<script>
    window.addEventListener('load', function () {
      setTimeout(function () {
        var gd = document.querySelector('.plotly-graph-div');
        Plotly.relayout(gd, {'scene.camera': {eye: {x: 0.1, y: 2.2, z: 0.3}}}).then(function () {
          setTimeout(function () {
            var out = document.createElement('pre');
            out.id = 'probe';
            out.textContent = JSON.stringify(
              [gd.layout.scene2.camera.eye, gd.layout.scene3.camera.eye]);
            document.body.appendChild(out);
          }, 500);
        });
      }, 1000);
    });
    </script></body>"""
    html = page.read_text(encoding="utf-8").replace("</body>", probe, 1)
    page.write_text(html, encoding="utf-8")
    proc = subprocess.run(
        [
            chromium(),
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--enable-unsafe-swiftshader",
            "--use-angle=swiftshader",
            "--virtual-time-budget=10000",
            "--dump-dom",
            page.as_uri(),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    found = re.search(r'<pre id="probe">([^<]*)</pre>', proc.stdout)
    assert found, proc.stdout[-2000:]
    eyes = json.loads(found.group(1).replace("&quot;", '"'))
    assert eyes == [{"x": 0.1, "y": 2.2, "z": 0.3}] * 2


def test_saturation_note():
    from dmd_jax.render import saturation_note

    assert saturation_note((0.0, 10.0), [np.array([1.0, 5.0])]) == ""
    assert saturation_note((0.0, 10.0), [np.array([1.0, 50.0])]) == "top colour: 10 and above"
    assert saturation_note((-3.39187, 3.39187), [np.array([-9.0, 9.0])]) == (
        "end colours: below -3.39 and above 3.39"
    )

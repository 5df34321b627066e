"""`dmd-jax render` cameras and zooms (issue 66 item 3) and its panel size (issue 65
family 8): a camera facing a scan (`--view auto`, `--view x,y,z` in `simulate_scan`'s
convention), a zoom on a point (`--zoom-at`) or where the panels differ (`--zoom auto`),
every `--panel-size` of the documented range. Checked on the pixels."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

import dmd_jax
from dmd_jax.cli import main
from dmd_jax.io import save_mesh
from dmd_jax.render import (
    _camera,
    auto_view,
    most_different_face,
    render_meshes,
    view_angles,
)


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def drawn(path) -> np.ndarray:
    """`[h, w]` bool: the pixels something was drawn on (not the white background)."""
    with Image.open(path) as image:
        return ~np.all(np.asarray(image.convert("RGB")) >= 250, axis=-1)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Overlap of two drawn masks, each resampled to 64 x 64 (a panel's shape follows
    the mesh's projected extent, so two views may differ in size)."""

    def square(m):
        return np.asarray(Image.fromarray(m.astype(np.uint8) * 255).resize((64, 64))) > 127

    a, b = square(a), square(b)
    return float((a & b).sum() / (a | b).sum())


def lumpy_body():
    """A closed, lopsided body (an ellipsoid with a bump): no view looks like another."""
    from conftest import icosphere

    v, f = icosphere(3)
    v = v * [1.0, 0.7, 0.45]
    v = v + 0.3 * np.exp(-8 * np.sum((v - [0.6, 0.3, 0.3]) ** 2, axis=1))[:, None] * v
    return v, f


@pytest.fixture(scope="module")
def scan():
    v, f = lumpy_body()
    return dmd_jax.simulate_scan(3, v, f, view=[0.3, -0.5, -0.8], resolution=96)


def test_view_is_where_the_camera_looks():
    """The camera sits on the side it looks from (`simulate_scan`'s convention), about
    either up axis."""
    rng = np.random.default_rng(0)
    for d in rng.standard_normal((20, 3)):
        towards, _, _ = _camera(*view_angles(d, "z"))
        np.testing.assert_allclose(towards, -d / np.linalg.norm(d), atol=1e-12)
        towards_y, _, _ = _camera(*view_angles(d, "y"))
        # Y-up coordinates are turned so that +Y is +Z: (x, y, z) -> (x, -z, y).
        u = -d / np.linalg.norm(d)
        np.testing.assert_allclose(towards_y, [u[0], -u[2], u[1]], atol=1e-12)
    with pytest.raises(ValueError, match="view"):
        view_angles([0, 0, 0])
    with pytest.raises(ValueError, match="view"):
        view_angles([1, np.nan, 0])


def test_auto_view_faces_a_scan_and_keeps_the_default_for_a_closed_mesh(scan):
    look = auto_view([(scan.noisy, scan.faces)])
    assert look is not None and float(look @ scan.view) > 0.9
    assert auto_view([lumpy_body()]) is None


def test_scan_rendered_with_view_auto_is_seen_from_its_sensor(scan, tmp_path):
    """Seen from its sensor, a scan covers the picture as it covered the depth image;
    `view="auto"` draws nearly the same pixels, the old default far fewer."""
    mesh = [(scan.noisy, scan.faces)]
    kw = dict(up="z", panel_size=1.5, dpi=60)
    own = drawn(render_meshes(mesh, tmp_path / "own.png", view=scan.view, **kw))
    auto = drawn(render_meshes(mesh, tmp_path / "auto.png", view="auto", **kw))
    behind = drawn(render_meshes(mesh, tmp_path / "behind.png", view=-scan.view, **kw))
    default = drawn(render_meshes(mesh, tmp_path / "default.png", **kw))
    assert own.mean() > 0.5 and auto.mean() > 0.5
    same = iou(own, auto)
    assert same > 0.9, same
    # From behind the silhouette is the mirror image, not the same picture.
    assert iou(own, behind) < same
    assert default.mean() < own.mean()


def test_cli_view_auto_is_the_default_and_matches_the_scans_own_view(scan, tmp_path, capsys):
    src = tmp_path / "scan.ply"
    save_mesh(src, scan.noisy, scan.faces)
    own_arg = "--view=" + ",".join(f"{x:.17g}" for x in scan.view)
    for name, extra in [("own", [own_arg]), ("auto", ["--view", "auto"]), ("plain", [])]:
        code, _, err = run(
            capsys, "render", src, "-o", tmp_path / f"{name}.png", "--no-zoom", "--up", "z",
            "--panel-size", "1.5", *extra,
        )  # fmt: skip
        assert code == 0, err
    own, auto, plain = (drawn(tmp_path / f"{n}.png") for n in ("own", "auto", "plain"))
    assert iou(own, auto) > 0.9
    assert np.array_equal(auto, plain)  # --view auto is the default


def grid_with_a_hole(hole=(14, 6)):
    """A flat 20 x 20 grid on [0, 1]^2 at z = 0, one cell (14, 6) left open."""
    n = 21
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], axis=1)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            if (i, j) == hole:
                continue
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            faces += [[a, b, c], [a, c, d]]
    centre = np.array([(hole[0] + 0.5) / (n - 1), (hole[1] + 0.5) / (n - 1), 0.0])
    return v, np.array(faces), centre


def test_zoom_at_puts_the_point_in_the_middle_of_the_inset(tmp_path):
    """The zoom row (the lower half: no title, no values) is centred on the point: on the
    hole its middle pixel is background, on the surface beside it, surface."""
    v, f, hole = grid_with_a_hole()
    kw = dict(view=[0, 0, -1], up="z", panel_size=2.0, dpi=50, crop_size=0.08)
    for point, open_middle in [(hole, True), (hole + [0.2, 0.0, 0.0], False)]:
        path = render_meshes([(v, f)], tmp_path / "z.png", zoom_at=point, overwrite=True, **kw)
        mask = drawn(path)
        h, w = mask.shape
        inset = mask[h // 2 :]
        middle = inset[inset.shape[0] // 2 - 1 : inset.shape[0] // 2 + 2, w // 2 - 1 : w // 2 + 2]
        assert not middle.any() if open_middle else middle.all(), point
        assert inset.mean() > 0.8  # the rest of the inset is the grid
    with pytest.raises(ValueError, match="zoom_at"):
        render_meshes([(v, f)], tmp_path / "x.png", zoom_at=[5.0, 5.0, 5.0])
    with pytest.raises(ValueError, match="zoom_at"):
        render_meshes([(v, f)], tmp_path / "x.png", zoom_at=[0.0, 1.0])


def test_zoom_auto_goes_where_the_panels_differ():
    v, f, _ = grid_with_a_hole()
    bumped = v.copy()
    near = np.linalg.norm(v[:, :2] - [0.25, 0.75], axis=1) < 0.12
    bumped[near, 2] += 0.03 * np.random.default_rng(0).standard_normal(near.sum())
    face = most_different_face([(bumped, f), (v, f)], elev=90.0, azim=0.0, up="z")
    assert np.linalg.norm(v[f[face]].mean(axis=0)[:2] - [0.25, 0.75]) < 0.15


def test_no_empty_row_without_gt(scan, tmp_path, capsys):
    src = tmp_path / "scan.ply"
    save_mesh(src, scan.noisy, scan.faces)
    save_mesh(tmp_path / "clean.ply", scan.clean, scan.faces)
    out = tmp_path / "r.png"
    code, _, err = run(
        capsys, "render", src, tmp_path / "clean.ply", "-o", out, "--zoom", "auto",
        "--panel-size", "1.5",
    )  # fmt: skip
    assert code == 0, err
    mask = drawn(out)
    title = int(0.3 * 110)  # the title strip, _TITLE_IN inches at 110 dpi
    rows = np.array_split(mask[title:], 2)  # shaded and zoom, nothing else
    assert len(rows) == 2 and all(r.mean() > 0.3 for r in rows), [r.mean() for r in rows]
    assert mask[-mask.shape[0] // 10 :].mean() > 0.1  # no blank strip or row at the bottom


@pytest.mark.parametrize("size", ["0.5", "1", "20"])
def test_every_documented_panel_size_is_drawn(size, tmp_path, capsys):
    v, f, _ = grid_with_a_hole()
    save_mesh(tmp_path / "g.off", v, f)
    for ext in (".png", ".html") if size != "20" else (".png",):
        out = tmp_path / f"r{ext}"
        code, _, err = run(capsys, "render", tmp_path / "g.off", "-o", out, "--panel-size", size)
        assert code == 0, err
        assert out.stat().st_size > 0


@pytest.mark.parametrize("size", ["0.49", "0.01", "0.001", "20.5"])
def test_panel_sizes_outside_the_range_are_refused_naming_the_option(size, tmp_path, capsys):
    v, f, _ = grid_with_a_hole()
    save_mesh(tmp_path / "g.off", v, f)
    code, out, err = run(
        capsys, "render", tmp_path / "g.off", "-o", tmp_path / "r.png", "--panel-size", size
    )
    assert code == 2 and out == ""
    (line,) = err.strip().splitlines()
    assert "--panel-size must be in [0.5, 20] inches" in line
    assert not (tmp_path / "r.png").exists()


def test_render_api_bounds_panel_size_and_dpi(tmp_path):
    v, f, _ = grid_with_a_hole()
    assert render_meshes([(v, f)], tmp_path / "a.png", panel_size=0.5, dpi=30).stat().st_size
    for kwargs, word in [
        ({"panel_size": 0.01}, "panel_size"),
        ({"dpi": 5}, "dpi"),
        ({"dpi": float("nan")}, "dpi"),
        ({"view": "behind"}, "view"),
        ({"zoom": "sharp"}, "zoom"),
        ({"zoom": "auto", "crop_face": 0}, "one of"),
    ]:
        with pytest.raises(ValueError, match=word):
            render_meshes([(v, f)], tmp_path / "b.png", **kwargs)
    assert not (tmp_path / "b.png").exists()


@pytest.mark.parametrize(
    "argv, word",
    [
        (["--view", "1,2"], "--view"),
        (["--view", "a,b,c"], "--view"),
        (["--view", "0,0,0"], "--view"),
        (["--view=nan,0,1"], "--view"),
        (["--view", "0,0,1", "--elev", "10"], "--view"),
        (["--zoom-at", "1,1"], "--zoom-at"),
        (["--zoom-at", "50,50,50"], "--zoom-at"),
        (["--zoom-at", "0.5,0.5,0", "--zoom", "auto"], "--zoom-at"),
    ],
)
def test_cli_refuses_bad_views_and_zooms_in_one_line(argv, word, tmp_path, capsys):
    v, f, _ = grid_with_a_hole()
    save_mesh(tmp_path / "g.off", v, f)
    code, out, err = run(capsys, "render", tmp_path / "g.off", "-o", tmp_path / "r.png", *argv)
    assert code == 2 and out == ""
    (line,) = err.strip().splitlines()
    assert word in line, line
    assert not (tmp_path / "r.png").exists()

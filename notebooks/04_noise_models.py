# %% [markdown]
# # 04 · Noise models, noise units, and how the metrics respond
#
# `dmd_jax.noise.add_noise_jax(key, vertices, faces, kind, level, units=...)` moves every
# coordinate by $\text{level}\cdot u\cdot X$, where $X$ is drawn independently per
# coordinate from one of four unit distributions and $u$ is the length one level unit
# stands for:
#
# | kind | $X$ | $E[X^2]$ |
# |---|---|---|
# | `gaussian` | $N(0, 1)$ | 1 |
# | `uniform` | $U(-1, 1)$ | 1/3 |
# | `gamma` | $\pm\Gamma(\text{shape } 2, \text{rate } 2)$, random sign | 1.5 |
# | `impulse` | $\delta(p, q)$: $\pm 1$ w.p. $p$ and $q$, else 0 ($p = q = 0.15$) | $p + q = 0.3$ |
#
# * `units="canonical"` (the paper's convention): $u$ is the longest side of the
#   bounding box, so levels are lengths in the canonical frame;
# * `units="edge"` (the convention of the CNR and GCN-Denoiser benchmarks): $u$ is the
#   mesh's mean edge length.
#
# Every draw comes from the `jax.random` key passed in, so the same key gives the same
# noise. The module docstring explains how the parametrisations were read off the
# paper's noise table (its reference errors are $\text{level}^2 E[X^2]$).

# %%
import tempfile
from pathlib import Path

import jax
import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from IPython.display import Image, display

import dmd_jax
from dmd_jax import noise
from dmd_jax.config import preset
from dmd_jax.data import generate_shape
from dmd_jax.mesh import mean_edge_length
from dmd_jax.metrics import (
    DEFAULT_METRICS,
    NORMAL,
    VERTEX,
    face_normal_errors_deg,
    format_metric,
    mesh_metrics,
    metric_header,
)
from dmd_jax.render import render_meshes

np.set_printoptions(precision=4, suppress=True, linewidth=100)
TMP = tempfile.TemporaryDirectory(prefix="dmd_nb04_")
KINDS = noise.PAPER_NOISE_KINDS  # the four per-coordinate laws; "scanner" comes last
SECOND_MOMENT = {"gaussian": 1.0, "uniform": 1 / 3, "gamma": 1.5, "impulse": 0.3}


def show_render(name, meshes, **kwargs):
    """Renders with dmd_jax.render_meshes into a temporary PNG and shows it."""
    backend = matplotlib.get_backend()
    path = render_meshes(meshes, Path(TMP.name) / f"{name}.png", overwrite=True, **kwargs)
    matplotlib.use(backend)  # render_meshes switches pyplot to Agg; keep inline plots working
    display(Image(filename=str(path)))


# %% [markdown]
# ## The four unit distributions
#
# 200 000 draws of each $X$; the printed second moments are the factors that turn a
# level into a per-coordinate mean squared displacement.

# %%
key = jax.random.PRNGKey(0)
fig, axes = plt.subplots(1, 4, figsize=(9, 2.2))
for ax, kind in zip(axes, KINDS, strict=True):
    x = np.asarray(noise.unit_noise(jax.random.fold_in(key, KINDS.index(kind)), (200_000,), kind))
    print(
        f"{kind:8s} mean {x.mean():+.4f}  "
        f"E[X²] {np.mean(x**2):.4f} (theory {SECOND_MOMENT[kind]:.4f})"
        f"  share of zeros {np.mean(x == 0):.2f}"
    )
    ax.hist(x, bins=np.linspace(-4, 4, 81), density=True, color="tab:blue")
    ax.set_title(kind, fontsize=10)
    ax.set_yticks([])
fig.tight_layout()
plt.show()

# %%
# The text below: second moments as tabulated, gamma never zero, impulse zero 70 % of the
# time and exactly ±1 otherwise.
for kind in KINDS:
    x = np.asarray(noise.unit_noise(jax.random.fold_in(key, KINDS.index(kind)), (200_000,), kind))
    assert abs(np.mean(x**2) / SECOND_MOMENT[kind] - 1) < 0.02, kind
    if kind == "gamma":
        assert np.mean(x == 0) == 0
    if kind == "impulse":
        assert abs(np.mean(x == 0) - 0.7) < 0.01 and np.all(np.abs(x[x != 0]) == 1)

# %% [markdown]
# Gamma noise has no mass near zero (the magnitude is $\Gamma(2, 2)$, mean 1) and a long
# tail; impulse noise leaves 70 % of the coordinates alone and moves the others by
# exactly one level.
#
# ## Levels in the canonical frame
#
# A procedural blob with about a thousand vertices (`generate_shape` returns it in its
# canonical frame already). For each kind at the five training levels of
# `noise.PAPER_LEVELS`, the per-coordinate mean squared error of the noisy mesh (the
# `vertex (×1e-4)` metric of `dmd-jax evaluate`, the paper's scale) against
# $\text{level}^2E[X^2]$:

# %%
blob_v, blob_f = generate_shape("blob", seed=0, instance=0, min_vertices=800, max_vertices=1200)
print(
    f"blob: {len(blob_v)} vertices, "
    f"mean edge length {mean_edge_length(blob_v, blob_f):.4f} (canonical frame)"
)

rows = []
print(f"{'kind':8s} {'level':>6s} {metric_header(VERTEX):>15s} {'level²·E[X²] (×1e-4)':>21s}")
for kind in KINDS:
    for level in noise.PAPER_LEVELS[kind]:
        noisy = np.asarray(
            noise.add_noise_jax(jax.random.fold_in(key, 100), blob_v, blob_f, kind, level)
        )
        m = mesh_metrics(noisy, blob_v, blob_f)
        rows.append((kind, level, m))
        predicted = level**2 * SECOND_MOMENT[kind]
        print(
            f"{kind:8s} {level:6.3f} "
            f"{format_metric(VERTEX, m[VERTEX.key]):>15s} {format_metric(VERTEX, predicted):>21s}"
        )

# "Match to within sampling noise, the ratio the same along a kind's rows": within 5 %,
# and one ratio per kind.
for kind in KINDS:
    ratios = [m[VERTEX.key] / (lv**2 * SECOND_MOMENT[kind]) for k, lv, m in rows if k == kind]
    assert all(abs(r - 1) < 0.05 for r in ratios), (kind, ratios)
    assert np.ptp(ratios) < 1e-5 * ratios[0], (kind, ratios)

# %% [markdown]
# The measured errors match the prediction to within sampling noise (one draw over a
# few thousand coordinates; the same key is used at every level, so the ratio is the
# same along a kind's rows). The level fixes the noise's energy only together with the
# kind: a gamma level of 0.04 is as strong as a Gaussian $\sigma$ of
# $0.04\sqrt{1.5} \approx 0.049$.
#
# ## What the noise looks like
#
# One draw of each kind at a matched strength: the level chosen so that the RMS
# displacement per coordinate is 0.01 (a hundredth of the longest side). Faces are
# coloured by the angle between their normal and the clean mesh's.

# %%
rms = 0.01
panels, errors = [(blob_v, blob_f)], [None]  # None: plain grey shading
for kind in KINDS:
    level = rms / np.sqrt(SECOND_MOMENT[kind])
    noisy = np.asarray(noise.add_noise_jax(jax.random.fold_in(key, 7), blob_v, blob_f, kind, level))
    panels.append((noisy, blob_f))
    errors.append(face_normal_errors_deg(noisy, blob_v, blob_f))
show_render(
    "kinds",
    panels,
    titles=["clean"] + [f"{k} {rms / np.sqrt(SECOND_MOMENT[k]):.3f}" for k in KINDS],
    face_values=errors,
    value_range=(0, 60),
    panel_size=1.8,
)

# The text below: at a matched RMS the four kinds disturb the normals alike (within 10 %
# of their mean), and impulse noise moves about two thirds of the vertices (0.7³ of
# them keep all three coordinates; float32 round-off aside).
kind_errors = np.array([e.mean() for e in errors[1:]])
assert np.all(np.abs(kind_errors / kind_errors.mean() - 1) < 0.1), kind_errors
moved = np.mean(np.any(np.abs(panels[-1][0] - blob_v) > 1e-6, axis=1))
assert abs(moved - (1 - 0.7**3)) < 0.05, moved

# %% [markdown]
# At a matched RMS the four kinds look much alike on the surface, even impulse noise:
# with $p + q = 0.3$ per coordinate, a vertex keeps all three coordinates with
# probability $0.7^3 \approx 0.34$ only, so two thirds of the vertices move. What
# differs is the distribution of the individual displacements (the histograms above),
# which matters to a filter that treats large and small displacements differently.
#
# ## Canonical units versus edge units
#
# The same blob remeshed at two resolutions. A canonical level is the same *length* on
# both, so it is a larger fraction of an edge on the fine mesh; an edge level scales
# with the edges. The normal error depends mostly on the displacement relative to the
# edge length, which is why the CNR-style benchmarks state levels in edge units.

# %%
resolutions = {
    "coarse": generate_shape("blob", seed=0, instance=0, min_vertices=500, max_vertices=700),
    "fine": generate_shape("blob", seed=0, instance=0, min_vertices=3000, max_vertices=4000),
}
edge = {name: mean_edge_length(v, f) for name, (v, f) in resolutions.items()}
for name, (v, _) in resolutions.items():
    print(f"{name:6s} {len(v):5d} vertices, mean edge length {edge[name]:.4f}")

canonical_levels = [0.0025, 0.005, 0.01, 0.02]
edge_levels = list(noise.EDGE_LEVELS)
normal_error = {}
for name, (v, f) in resolutions.items():
    for units, levels in (("canonical", canonical_levels), ("edge", edge_levels)):
        normal_error[name, units] = [
            face_normal_errors_deg(
                np.asarray(
                    noise.add_noise_jax(
                        jax.random.fold_in(key, 3), v, f, "gaussian", lv, units=units
                    )
                ),
                v,
                f,
            ).mean()
            for lv in levels
        ]

fig, axes = plt.subplots(1, 2, figsize=(8, 2.8), sharey=True)
for ax, units, levels in ((axes[0], "canonical", canonical_levels), (axes[1], "edge", edge_levels)):
    for name in resolutions:
        ax.plot(
            levels,
            normal_error[name, units],
            "o-",
            label=f"{name} ({len(resolutions[name][0])} vertices)",
        )
    ax.set_xlabel(f"Gaussian σ, {units} units")
    ax.set_title(f"units={units!r}", fontsize=10)
axes[0].set_ylabel("mean normal error (deg)")
axes[0].legend(fontsize=8)
fig.tight_layout()
plt.show()
for name in resolutions:
    print(
        f"{name:6s}: edge level 0.3 = canonical σ {0.3 * edge[name]:.4f};  "
        f"canonical σ 0.01 = {0.01 / edge[name]:.2f} edge lengths"
    )

# The text below: at each canonical σ the fine mesh's normal error is at least twice
# the coarse mesh's; at each edge level the two are within 10 % of each other.
coarse, fine = (np.array(normal_error[n, "canonical"]) for n in ("coarse", "fine"))
assert np.all(fine > 2 * coarse), (coarse, fine)
coarse, fine = (np.array(normal_error[n, "edge"]) for n in ("coarse", "fine"))
assert np.all(np.abs(fine / coarse - 1) < 0.1), (coarse, fine)

# %% [markdown]
# Left: at one canonical $\sigma$ the fine mesh's normals are far more disturbed than
# the coarse mesh's. Right: in edge units the two curves nearly coincide. Training
# (`dmd_jax.pipeline`) draws each mesh's noise in edge units with probability
# `NoiseConfig.p_edge`, in canonical units otherwise: the bundled `small` recipe draws
# edge units for 85 % of its meshes (60 % of those along the vertex normals, the
# benchmark protocol), clean inputs for 10 %, and capped canonical levels for the rest.

# %%
recipe = preset("small").noise
print(f"p_edge {recipe.p_edge}, p_normal {recipe.p_normal}, p_clean {recipe.p_clean}")
assert (recipe.p_edge, recipe.p_normal, recipe.p_clean) == (0.85, 0.6, 0.1)

# %% [markdown]
# ## How the three metrics respond
#
# The paper reports three errors (`dmd_jax.metrics.mesh_metrics`): the mean squared
# vertex distance (reported per coordinate), the mean angle between corresponding face
# normals in degrees, and the chamfer distance between the vertex sets. Below, every
# kind over a range of levels on the blob, plotted against the RMS displacement per
# coordinate, $\text{level}\sqrt{E[X^2]}$.

# %%
rms_grid = np.geomspace(0.0005, 0.05, 9)
response = {kind: [] for kind in KINDS}
for kind in KINDS:
    for i, target in enumerate(rms_grid):
        level = target / np.sqrt(SECOND_MOMENT[kind])
        noisy = np.asarray(
            noise.add_noise_jax(jax.random.fold_in(key, 1000 + i), blob_v, blob_f, kind, level)
        )
        response[kind].append(mesh_metrics(noisy, blob_v, blob_f))

print(f"{metric_header(NORMAL)} at RMS   " + " ".join(f"{x:7.4f}" for x in rms_grid))
for kind in KINDS:
    print(f"{kind:25s}" + " ".join(f"{m[NORMAL.key]:7.1f}" for m in response[kind]))

fig, axes = plt.subplots(1, 3, figsize=(10, 2.9))
for kind in KINDS:
    for ax, spec in zip(axes, DEFAULT_METRICS, strict=True):
        values = [m[spec.key] * spec.scale for m in response[kind]]
        ax.plot(rms_grid, values, "o-", ms=3, label=kind)
axes[0].plot(rms_grid, rms_grid**2 * VERTEX.scale, "k--", lw=1, label="RMS²")
axes[2].plot(rms_grid, 6 * rms_grid**2 * DEFAULT_METRICS[2].scale, "k--", lw=1, label="6 RMS²")
axes[2].legend(fontsize=7)
# Titles, units and scaling of `dmd-jax evaluate` (dmd_jax.metrics).
for ax, title in zip(axes, [metric_header(s) for s in DEFAULT_METRICS], strict=True):
    ax.set_xscale("log")
    ax.set_xlabel("RMS displacement per coordinate")
    ax.set_title(title, fontsize=10)
axes[0].set_yscale("log")
axes[2].set_yscale("log")
axes[0].legend(fontsize=7)
fig.tight_layout()
plt.show()

# %%
# What the bullets below say, checked on these numbers.
blob_edge = mean_edge_length(blob_v, blob_f)
for kind in KINDS:
    vertex = np.array([m[VERTEX.key] for m in response[kind]])
    normal = np.array([m[NORMAL.key] for m in response[kind]])
    chamfer = np.array([m["chamfer"] for m in response[kind]])
    # Vertex error on the RMS² line (one draw per point: within 10 %).
    assert np.all(np.abs(vertex / rms_grid**2 - 1) < 0.1), kind
    # Normal error roughly proportional to the RMS up to a tenth of an edge (slope of
    # log-log between 0.8 and 1.2), about 10° there, near 90° (over 70°) at one edge.
    small = rms_grid <= 0.1 * blob_edge
    slope = np.polyfit(np.log(rms_grid[small]), np.log(normal[small]), 1)[0]
    assert 0.8 < slope < 1.2, (kind, slope)
    assert 7 < np.interp(0.1 * blob_edge, rms_grid, normal) < 13, kind
    assert np.interp(blob_edge, rms_grid, normal) > 70, kind
    # Chamfer on the 6 RMS² line while the noise is small, below it at an edge length.
    assert np.all(np.abs(chamfer[small] / (6 * rms_grid[small] ** 2) - 1) < 0.1), kind
    assert chamfer[-1] < 0.5 * 6 * rms_grid[-1] ** 2, kind
# "Nearly indistinguishable at a matched RMS": every metric within 10 % across kinds
# while the RMS is below a third of an edge.
for key in (VERTEX.key, NORMAL.key, "chamfer"):
    table = np.array([[m[key] for m in response[kind]] for kind in KINDS])
    table = table[:, rms_grid < blob_edge / 3]
    assert np.all(np.abs(table / table.mean(0) - 1) < 0.1), key

# %% [markdown]
# * **Vertex error** is the noise energy itself: every kind lies on the dashed RMS²
#   line.
# * **Normal error** depends on the displacement relative to the edge length (the
#   blob's mean edge length, about 0.05, was printed above): roughly proportional to
#   the RMS up to a tenth of an edge (about 10° there), then steeper, and close to
#   90°, the mean angle between unrelated directions, once the RMS reaches an edge
#   length.
# * **Chamfer distance** sums, in both directions, the squared distance of each vertex
#   to the *nearest* vertex of the other set. While the nearest vertex is the
#   counterpart it equals twice the mean squared vertex distance, $2\cdot3\,
#   \text{RMS}^2$ (dashed line); once the noise is comparable to the edge length a
#   moved vertex often finds a closer stranger, and the chamfer distance falls below
#   that line.
# * At a matched RMS the four kinds are nearly indistinguishable in all three metrics
#   (the table above), so the level-to-RMS conversion is what makes results with
#   different kinds comparable.
#
# A denoiser can trade one metric against another: uniform smoothing lowers the vertex
# error while rounding off sharp edges, which the normal error punishes. Notebook 06
# puts DMD-Net and two classic filters through all three.

# %% [markdown]
# ## Scanner noise and a simulated depth scan
#
# Real scans are not noised per coordinate. The `scanner` kind (`noise.ScannerModel`)
# moves every vertex along **one view direction** by a smooth random field (correlation
# length 6 mean edges: neighbours alike over 4-8 rings, faded by ~16) plus a small white
# part, growing where the surface is seen at a grazing angle and rounded to depth steps;
# its rms is `level` mean edges. `dmd_jax.simulate_scan` goes further: it renders the
# clean mesh into a depth map from a view, triangulates the depth map back (open
# boundaries, holes behind occluders, slivers at grazing angles) and adds the scanner
# noise in depth, keeping the exact surface point of every pixel as the ground truth.
# Below: the blob with scanner noise, then a scan of it seen from two angles, faces
# coloured by their normal error against the scan's own clean surface.

# %%
scanner = dmd_jax.add_noise(3, blob_v, blob_f, "scanner", 0.5, units="edge")
scan = dmd_jax.simulate_scan(3, blob_v, blob_f, resolution=96, level=0.5)
moved = scanner - blob_v
axis = np.linalg.svd(moved, full_matrices=False)[2][0]
print(
    f"scanner noise: rms {np.sqrt(np.mean(np.sum(moved**2, 1))) / blob_edge:.2f} mean edges, "
    f"share of the motion along one axis {np.sum((moved @ axis) ** 2) / np.sum(moved**2):.3f}"
)
print(
    f"scan from view {np.round(scan.view, 3)}: {len(scan.clean)} vertices, "
    f"{len(scan.faces)} faces (the blob: {len(blob_v)} / {len(blob_f)})"
)
# Every scan vertex moved along the view only; the clean scan lies on the blob.
d = scan.noisy - scan.clean
assert np.abs(d - np.outer(d @ scan.view, scan.view)).max() < 1e-12
assert np.sum((moved @ axis) ** 2) / np.sum(moved**2) > 0.999
turn = np.array([[-0.5, -0.866, 0.0], [0.866, -0.5, 0.0], [0.0, 0.0, 1.0]])  # 120° about z
show_render(
    "scan",
    [
        (blob_v, blob_f),
        (scanner, blob_f),
        (scan.noisy, scan.faces),
        (scan.noisy @ turn.T, scan.faces),
    ],
    titles=["clean", "scanner 0.5", "scan 0.5", "scan 0.5, turned"],
    face_values=[
        None,
        face_normal_errors_deg(scanner, blob_v, blob_f),
        face_normal_errors_deg(scan.noisy, scan.clean, scan.faces),
        face_normal_errors_deg(scan.noisy, scan.clean, scan.faces),
    ],
    value_range=(0, 60),
    panel_size=1.8,
)

# %% [markdown]
# # 03 · Normals, curvature and the feature extractor's targets
#
# The feature extractor of DMD-Net is trained to recover, for every vertex of the
# *clean* mesh, five numbers: the unit normal, the mean curvature $\kappa_H$ and the
# Gaussian curvature $\kappa_G$. `dmd_jax.geometry` computes them with the discrete
# operators of Meyer, Desbrun, Schröder and Barr (2003), the ones appendix C of the
# paper writes down:
#
# * vertex normal: the area-weighted mean of the incident face normals;
# * $\kappa_H(v) = \lvert\sum_u(\cot\alpha_{vu} + \cot\beta_{vu})(p_v - p_u)\rvert /
#   (4A_\text{mixed}(v))$, unsigned (`signed_mean_curvature` adds the sign);
# * $\kappa_G(v) = (2\pi - \sum_f\theta_f(v)) / A_\text{mixed}(v)$, the angle defect over
#   the mixed Voronoi area.
#
# We check them on a sphere and a torus, whose curvatures are known in closed form,
# then look at a CAD part, where sharp edges make the curvature targets span orders of
# magnitude.

# %%
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib
import matplotlib.pyplot as plt
import numpy as np
import trimesh
from IPython.display import Image, display

from dmd_jax import geometry
from dmd_jax.data import generate_shape
from dmd_jax.graph import vertex_edges
from dmd_jax.mesh import canonical_frame
from dmd_jax.render import render_meshes

jax.config.update("jax_enable_x64", True)  # float64: the checks below are about the formulas
np.set_printoptions(precision=4, suppress=True, linewidth=100)
TMP = tempfile.TemporaryDirectory(prefix="dmd_nb03_")


def show_render(name, meshes, **kwargs):
    """Renders with dmd_jax.render_meshes into a temporary PNG and shows it."""
    backend = matplotlib.get_backend()
    path = render_meshes(meshes, Path(TMP.name) / f"{name}.png", overwrite=True, **kwargs)
    matplotlib.use(backend)  # render_meshes switches pyplot to Agg; keep inline plots working
    display(Image(filename=str(path)))


@jax.jit
def _curvatures(v, f):
    return (
        geometry.vertex_normals(v, f),
        geometry.mean_curvature(v, f),
        geometry.signed_mean_curvature(v, f),
        geometry.gaussian_curvature(v, f),
    )


def curvatures(v, f):
    """(unit normals, unsigned κ_H, signed κ_H, κ_G) as NumPy arrays."""
    return tuple(np.asarray(x) for x in _curvatures(jnp.asarray(v), jnp.asarray(f)))


def euler_characteristic(v, f):
    return len(v) - len(vertex_edges(f, len(v))[0]) + len(f)


# %% [markdown]
# ## Unit sphere
#
# The outward normal at $p$ is $p$ itself, and both curvatures are 1 everywhere
# ($\kappa_H = 1/r$, $\kappa_G = 1/r^2$). An icosphere with 2562 vertices:

# %%
sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
sv, sf = np.asarray(sphere.vertices, float), np.asarray(sphere.faces, np.int32)
n, kh, kh_signed, kg = curvatures(sv, sf)
exact_n = sv / np.linalg.norm(sv, axis=1, keepdims=True)
angle = np.degrees(np.arccos(np.clip(np.sum(n * exact_n, axis=1), -1, 1)))
print(f"{len(sv)} vertices; normal error: max {angle.max():.2e} degrees")
for name, x in [("κ_H", kh), ("signed κ_H", kh_signed), ("κ_G", kg)]:
    print(f"{name:10s} mean {x.mean():.4f}  min {x.min():.4f}  max {x.max():.4f}  (exact 1)")

# What the text below says: normals within a fraction of a degree, κ_H exact to 1e-3,
# κ_G about 0.1 % high everywhere.
assert angle.max() < 1.0
assert np.abs(kh - 1).max() < 1e-3 and np.abs(kh_signed - 1).max() < 1e-3
assert 1.0005 < kg.min() and kg.max() < 1.002

# %% [markdown]
# All vertices of an icosphere lie on the sphere, but its triangles are not all alike:
# the area-weighted normals tilt by a fraction of a degree where the triangle sizes
# change, and $\kappa_G$ comes out about 0.1 % high (the angle defects sum to exactly
# $4\pi$, see Gauss–Bonnet below, but the mixed areas sum to the area of the polyhedron,
# slightly less than $4\pi$). The discrete operators converge to the smooth values as
# the mesh is refined.
#
# ## Torus
#
# A torus with major radius $R = 1$ and tube radius $r = 0.6$. At tube angle $\varphi$
# ($\varphi = 0$ on the outer equator, $\pi$ on the inner one) the curvatures are
#
# $$\kappa_G = \frac{\cos\varphi}{r(R + r\cos\varphi)}, \qquad
#   H = \frac{R + 2r\cos\varphi}{2r(R + r\cos\varphi)}.$$
#
# The inner side is saddle-shaped ($\kappa_G < 0$), and with a tube this fat the mean
# curvature $H$ changes sign there too: the unsigned $\kappa_H$ that the feature
# extractor learns is $|H|$.

# %%
R, r = 1.0, 0.6
torus = trimesh.creation.torus(major_radius=R, minor_radius=r, major_sections=72, minor_sections=36)
tv, tf = np.asarray(torus.vertices, float), np.asarray(torus.faces, np.int32)
phi = np.arctan2(tv[:, 2], np.hypot(tv[:, 0], tv[:, 1]) - R)
exact_kg = np.cos(phi) / (r * (R + r * np.cos(phi)))
exact_h = (R + 2 * r * np.cos(phi)) / (2 * r * (R + r * np.cos(phi)))
n, kh, kh_signed, kg = curvatures(tv, tf)

print(f"{len(tv)} vertices")
print(
    f"max |κ_G - exact|        = {np.abs(kg - exact_kg).max():.4f}  "
    f"(range of κ_G: {exact_kg.min():.3f} to {exact_kg.max():.3f})"
)
print(
    f"max |signed κ_H - exact| = {np.abs(kh_signed - exact_h).max():.4f}  "
    f"(range of H: {exact_h.min():.3f} to {exact_h.max():.3f})"
)
print(f"max |κ_H - |H||          = {np.abs(kh - np.abs(exact_h)).max():.4f}")
# "Follow the closed forms": within 2 % of each quantity's range, including the sign
# of H on both sides of the circles where it changes (φ = ±0.81π).
assert np.abs(kg - exact_kg).max() < 0.02 * np.ptp(exact_kg)
assert np.abs(kh_signed - exact_h).max() < 0.02 * np.ptp(exact_h)
assert np.all(kh_signed[np.abs(phi) > 0.85 * np.pi] < 0)
assert np.all(kh_signed[np.abs(phi) < 0.77 * np.pi] > 0)

order = np.argsort(phi)
fig, axes = plt.subplots(1, 2, figsize=(8, 2.8), sharex=True)
for ax, est, exact, name in [
    (axes[0], kh_signed, exact_h, "signed mean curvature"),
    (axes[1], kg, exact_kg, "Gaussian curvature"),
]:
    ax.plot(phi[order], exact[order], color="black", lw=1, label="exact")
    ax.scatter(phi, est, s=2, color="tab:orange", label="Meyer et al.")
    ax.axhline(0, color="grey", lw=0.5)
    ax.set_xlabel("tube angle φ (0 = outer equator)")
    ax.set_title(name, fontsize=10)
axes[0].legend(fontsize=8, markerscale=4)
fig.tight_layout()
plt.show()

# %% [markdown]
# The estimates follow the closed forms around the whole tube, including the sign
# change of $H$ on the inside, where $\cos\varphi = -R/2r$ ($\varphi \approx
# \pm0.81\pi$).
#
# ## Gauss–Bonnet
#
# The angle defects of a closed mesh sum to exactly $2\pi\chi$ (the discrete
# Gauss–Bonnet theorem; $\chi = V - E + F$), whatever the triangulation: $4\pi$ for the
# sphere, 0 for the torus. `geometry.angle_defect` is the numerator of $\kappa_G$.

# %%
bracket_v, bracket_f = generate_shape(
    "bracket", seed=0, instance=1, min_vertices=1000, max_vertices=2000
)
for name, (v, f) in {
    "sphere": (sv, sf),
    "torus": (tv, tf),
    "bracket": (bracket_v, bracket_f),
}.items():
    total = float(jax.jit(geometry.angle_defect)(jnp.asarray(v), jnp.asarray(f)).sum())
    chi = euler_characteristic(v, f)
    print(f"{name:8s} χ = {chi:3d}: Σ angle defect = {total:9.5f}, 2πχ = {2 * np.pi * chi:9.5f}")
    assert abs(total - 2 * np.pi * chi) < 1e-8, name  # exact, whatever the triangulation

# %% [markdown]
# ## A CAD part: sharp edges
#
# On a mechanical part most of the surface is flat or gently curved, and the curvature
# concentrates on the sharp edges and corners. A discrete vertex on a sharp edge has a
# tiny mixed area compared with the angle it turns, so its $\kappa_H$ and $\kappa_G$
# are large, and they grow as the mesh is refined. Below, the bracket in its canonical
# frame (longest side 1, the frame the network sees): vertices on a sharp edge (an
# incident dihedral angle above 30°) against the rest.

# %%
cv = canonical_frame(bracket_v).apply(bracket_v)
cf = bracket_f
n, kh, kh_signed, kg = curvatures(cv, cf)

# Dihedral angle of every edge shared by two faces, from the face normals.
face_n = np.asarray(jax.jit(geometry.face_normals)(cv, cf))
mesh = trimesh.Trimesh(cv, cf, process=False)
pairs, edge = mesh.face_adjacency, mesh.face_adjacency_edges
dihedral = np.degrees(
    np.arccos(np.clip(np.sum(face_n[pairs[:, 0]] * face_n[pairs[:, 1]], 1), -1, 1))
)
sharp = np.zeros(len(cv), bool)
sharp[edge[dihedral > 30].ravel()] = True

print(f"{len(cv)} vertices, {sharp.sum()} on sharp edges")
print("percentile        50        90        99       max")
for name, x in [
    ("|κ_H| smooth", kh[~sharp]),
    ("|κ_H| sharp", kh[sharp]),
    ("|κ_G| smooth", np.abs(kg[~sharp])),
    ("|κ_G| sharp", np.abs(kg[sharp])),
]:
    print(f"{name:13s}" + "".join(f"{v:10.3g}" for v in np.percentile(x, [50, 90, 99, 100])))

# The text's reading of this table: flat faces have zero curvature, edge vertices a large
# κ_H; κ_G vanishes along straight edges (the sharp median) and is large at corners.
assert np.median(kh[~sharp]) < 1e-9 and np.median(kh[sharp]) > 10
assert np.median(np.abs(kg[sharp])) < 1e-6 and np.abs(kg[sharp]).max() > 100

# %% [markdown]
# ## Colour maps
#
# Per-face values (the mean of the three corner values) rendered with
# `dmd_jax.render.render_meshes`, every mesh in its canonical frame. The values are
# compressed with $\operatorname{asinh}$, which is linear near 0 and logarithmic for
# large values, so the sphere's constant curvature, the torus's gradual change and the
# bracket's edges fit one colour scale. Mean curvature first (signed: dark means
# negative), then Gaussian curvature.

# %%
meshes = [(sv, sf), (tv, tf), (bracket_v, bracket_f)]
fields = {"signed κ_H": [], "κ_G": []}
for v, f in meshes:
    _, _, h, k = curvatures(canonical_frame(v).apply(v), f)
    fields["signed κ_H"].append(np.arcsinh(h[f].mean(axis=1)))
    fields["κ_G"].append(np.arcsinh(k[f].mean(axis=1)))
for name, values in fields.items():
    top = float(np.percentile(np.abs(np.concatenate(values)), 99))
    show_render(
        name.replace(" ", "_"),
        meshes,
        titles=["sphere", "torus", "bracket"],
        face_values=values,
        value_range=(-top, top),
        value_label=f"asinh({name})",
        panel_size=2.2,
    )

# The text below: the sphere is one colour (κ_H = 2, κ_G = 4 at diameter 1); the torus is
# positive outside and negative inside in both quantities; the bracket's edges have
# both signs of κ_H (convex and concave).
_, _, h_s, k_s = curvatures(canonical_frame(sv).apply(sv), sf)
assert np.allclose(h_s, 2, rtol=2e-3) and np.allclose(k_s, 4, rtol=3e-3)
_, _, h_t, k_t = curvatures(canonical_frame(tv).apply(tv), tf)
outer, inner = np.abs(phi) < 0.1 * np.pi, np.abs(phi) > 0.9 * np.pi
assert np.all(h_t[outer] > 0) and np.all(k_t[outer] > 0)
assert np.all(h_t[inner] < 0) and np.all(k_t[inner] < 0)
_, _, h_b, _ = curvatures(cv, cf)
assert h_b[sharp].min() < -1 and h_b[sharp].max() > 1

# %% [markdown]
# In the canonical frame the sphere has diameter 1, so $\kappa_H = 2$ and
# $\kappa_G = 4$ everywhere (one colour). The torus is bright outside and dark inside
# for both quantities. On the bracket, flat faces sit at the middle of the scale and the
# edges light up: convex edges positive, concave ones negative in $\kappa_H$; its
# $\kappa_G$ is near zero along straight edges (they bend the surface in one direction
# only) and large at the corners.
#
# ## The feature extractor's targets
#
# `geometry.vertex_features(vertices, faces)` stacks the five targets, `[n, 5]`, for the
# clean mesh in the canonical frame. The training step compares them with the feature
# extractor's output (`losses.feature_extractor_loss`, a squared error).

# %%
names = ["n_x", "n_y", "n_z", "κ_H", "κ_G"]
for label, (v, f) in zip(["sphere", "torus", "bracket"], meshes, strict=True):
    target = np.asarray(jax.jit(geometry.vertex_features)(canonical_frame(v).apply(v), f))
    print(
        f"{label}: |normal| = {np.linalg.norm(target[:, :3], axis=1).min():.6f} .. "
        f"{np.linalg.norm(target[:, :3], axis=1).max():.6f}"
    )
    for j in (3, 4):
        x = target[:, j]
        print(
            f"   {names[j]}: min {x.min():10.3g}  median {np.median(x):10.3g}  max {x.max():10.3g}"
            f"   asinh: min {np.arcsinh(x).min():6.2f}  max {np.arcsinh(x).max():6.2f}"
        )
    assert np.allclose(np.linalg.norm(target[:, :3], axis=1), 1, atol=1e-6)
    if label == "bracket":  # "several orders of magnitude": |κ_G| from ~0 to over 1000
        assert np.median(np.abs(target[:, 4])) < 1e-6 and np.abs(target[:, 4]).max() > 1e3

# %% [markdown]
# The normals are unit vectors, but the curvature columns of a CAD part span several
# orders of magnitude, so a squared error on the raw values is dominated by a handful
# of edge vertices. Two project choices follow from this: the feature extractor's normal
# output is normalised to unit length (`ModelConfig.normalize_fe_normals`), and the
# curvature targets can be learnt as $\operatorname{asinh}(\kappa)$ instead of the raw
# values (`LossConfig.feature_curvature = "asinh"`; the paper's setting is `"raw"`).
# Notebook 05 compares a trained feature extractor's output with these targets.

"""SYMSOL shapes, renderer and dataset writer (image2sphere.data.shapes, .symmetry, .raycast, .render).

Independent references: symmetry groups are checked by brute-force enumeration of the vertex-set
symmetries (numpy only); mark visibility against dense samples of the mark's surface and against the
rendered pixels; the renderer against analytic silhouette areas, depths, normals and Lambertian shades.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import math
import os

import numpy as np
import pytest
import torch
from PIL import Image

from image2sphere.data.raycast import (
    AMBIENT,
    DIFFUSE,
    LABEL_MARK_DISC,
    LABEL_MARK_DOT,
    LIGHT_DIRECTION,
    cast_rays,
    render,
)
from image2sphere.data.render import main, render_symsol, symsol_rotations
from image2sphere.data.shapes import (
    BOUND_RADIUS,
    CONE_APEX_HEIGHT,
    CONE_BASE_DEPTH,
    CONE_BASE_RADIUS,
    CYL_HALF_HEIGHT,
    CYL_RADIUS,
    MARK_DISC_COLOUR,
    MARK_DOT_COLOUR,
    SHAPES,
    SPHERE_RADIUS,
    SYMSOL_I_SHAPES,
    SYMSOL_II_SHAPES,
    shape_geometry,
)
from image2sphere.data.symmetry import equivalent_rotation_sets, equivalent_rotations, mark_visible, symmetry_group

render_module = importlib.import_module("image2sphere.data.render")  # the package attribute is the function

GROUP_SIZES = {"tet": 12, "cube": 24, "icosa": 60, "cone": 360, "cyl": 720, "tetX": 12, "cylO": 720, "sphereX": 577}


@pytest.fixture(autouse=True)
def _one_thread(single_thread):
    """One intra-op thread: the renderer's many small ops crawl when a 2-thread pool shares busy cores."""
    yield


def haar(n: int, seed: int) -> torch.Tensor:
    from scipy.spatial.transform import Rotation

    return torch.as_tensor(Rotation.random(n, random_state=seed).as_matrix(), dtype=torch.float64)


def rot_x(deg: float) -> torch.Tensor:
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=torch.float64)


def pixel_diff(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-pixel max channel difference in grey levels ``(..., H, W)``."""
    return (a.int() - b.int()).abs().amax(-1)


def assert_same_images(images: torch.Tensor, reference: torch.Tensor) -> None:
    d = pixel_diff(images, reference).float()  # [N, H, W]
    mean = d.mean(dim=(-1, -2))
    frac = (d > 4).float().mean(dim=(-1, -2))
    assert mean.max() < 0.5, f"mean abs difference up to {mean.max():.3f} grey levels"
    assert frac.max() < 0.005, f"up to {100 * frac.max():.2f}% of pixels differ by more than 4 levels"


def different_pixel_counts(images: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    return (pixel_diff(images, reference) > 8).sum(dim=(-1, -2))


def nearest_index(P: torch.Tensor, G: torch.Tensor, chunk: int = 65536) -> tuple[torch.Tensor, torch.Tensor]:
    """Index of the nearest element of ``G`` and the Frobenius distance, for each matrix of ``P``."""
    Gf = G.reshape(len(G), 9)
    idx, dist = [], []
    for Pc in P.reshape(-1, 9).split(chunk):
        d2 = (Pc * Pc).sum(1, keepdim=True) + (Gf * Gf).sum(1) - 2 * Pc @ Gf.T
        i = d2.argmin(dim=1)
        idx.append(i)
        dist.append((Pc - Gf[i]).norm(dim=1))  # exact distance to the nearest
    return torch.cat(idx), torch.cat(dist)


# --------------------------------------------------------------------------------------------------
# Groups and geometry
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", SHAPES)
def test_group_size_identity_and_closure(shape):
    G = symmetry_group(shape)
    assert G.dtype == torch.float64 and G.shape == (GROUP_SIZES[shape], 3, 3)
    assert torch.equal(G[0], torch.eye(3, dtype=torch.float64))
    eye = torch.eye(3, dtype=torch.float64)
    assert (G.transpose(1, 2) @ G - eye).abs().max() < 1e-12
    assert (torch.linalg.det(G) - 1).abs().max() < 1e-12
    _, self_dist = nearest_index(G[1:], G[:1])
    assert self_dist.min() > 1e-3, "identity listed twice"
    idx, _ = nearest_index(G, G)
    assert torch.equal(idx, torch.arange(len(G))), "duplicate elements"
    if shape == "sphereX":
        return  # a grid, not a group
    products = (G[:, None] @ G[None]).reshape(-1, 3, 3)
    if shape in ("cone", "cyl", "cylO"):  # look the product up by its turn angle about y and its flip
        flip = products[:, 1, 1] < 0
        sign = torch.where(flip, -1.0, 1.0).to(torch.float64)
        degrees = torch.rad2deg(torch.atan2(sign * products[:, 0, 2], products[:, 0, 0]))
        idx = torch.round(degrees).long() % 360 + 360 * flip.long()
        dist = (products - G[idx]).flatten(1).norm(dim=1)
    else:
        _, dist = nearest_index(products, G)
    assert dist.max() < 1e-9, f"{shape}: not closed under multiplication (off by {dist.max():.2e})"


def _vertex_set_symmetries(v: np.ndarray) -> np.ndarray:
    """All proper rotations mapping the vertex set onto itself, by brute force over vertex pairs."""

    def frame(a, b):
        e1 = a / np.linalg.norm(a)
        e2 = b - (b @ e1) * e1
        e2 /= np.linalg.norm(e2)
        return np.stack([e1, e2, np.cross(e1, e2)], axis=1)

    a, b = v[0], min(v[1:], key=lambda w: np.linalg.norm(w - v[0]))  # an edge
    base = frame(a, b)
    found = []
    for p in v:
        for q in v:
            if np.linalg.norm(p - q) < 1e-9 or abs(np.linalg.norm(p - q) - np.linalg.norm(a - b)) > 1e-9:
                continue
            S = frame(p, q) @ base.T
            moved = v @ S.T
            if np.abs(moved[:, None] - v[None]).sum(-1).min(1).max() < 1e-9:
                found.append(S)
    return np.array(found)


@pytest.mark.parametrize("shape", ["tet", "cube", "icosa", "tetX"])
def test_polyhedron_group_is_exactly_the_vertex_symmetries(shape):
    geom = shape_geometry(shape)
    v = geom.vertices.numpy()
    assert len(v) == {"tet": 4, "cube": 8, "icosa": 12, "tetX": 4}[shape]
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), BOUND_RADIUS, atol=1e-12)
    G = symmetry_group(shape).numpy()
    for S in G:  # every element maps the vertex set onto itself
        assert np.abs((v @ S.T)[:, None] - v[None]).sum(-1).min(1).max() < 1e-9
    generic = haar(1, seed=11)[0].numpy()
    assert np.abs((v @ generic.T)[:, None] - v[None]).sum(-1).min(1).max() > 1e-2
    brute = _vertex_set_symmetries(v)
    assert len(brute) == len(G)
    idx, dist = nearest_index(torch.as_tensor(brute), torch.as_tensor(G))
    assert dist.max() < 1e-9 and len(set(idx.tolist())) == len(G)
    # faces: merged coplanar triangles, every vertex inside every half-space, >= 3 vertices per face
    n, h = geom.plane_normals.numpy(), geom.plane_offsets.numpy()
    assert len(n) == {"tet": 4, "cube": 6, "icosa": 20, "tetX": 4}[shape]
    slack = h[None] - v @ n.T  # [V, F]
    assert slack.min() > -1e-9
    assert ((np.abs(slack) < 1e-9).sum(0) >= 3).all()


def test_shapes_fit_in_the_image_and_marks_break_symmetry():
    assert SYMSOL_I_SHAPES + SYMSOL_II_SHAPES == SHAPES
    assert math.hypot(CYL_RADIUS, CYL_HALF_HEIGHT) <= BOUND_RADIUS + 1e-12 and SPHERE_RADIUS <= BOUND_RADIUS
    for shape in SYMSOL_II_SHAPES:
        geom = shape_geometry(shape)
        centres = torch.stack([p.centre for p in geom.marks])  # [2, 3]
        G = symmetry_group(shape)
        moved = torch.einsum("gij,kj->gki", G[1:], centres)  # [G - 1, 2, 3]
        # the smallest move is cylO's 1-degree turn: 2 sin(0.5 deg) * radius = 0.0087
        assert (moved - centres).norm(dim=-1).amax(-1).min() > 0.005, f"{shape}: a symmetry fixes the mark"
    cyl = shape_geometry("cylO")
    assert all(abs(float(p.centre[1])) > p.radius for p in cyl.marks), "cylO mark must avoid mid-height"


def test_bad_arguments_raise_value_error():
    R = torch.eye(3, dtype=torch.float64)
    with pytest.raises(ValueError, match="tet, cube, icosa"):
        symmetry_group("dodeca")
    with pytest.raises(ValueError, match="shape"):
        render("sphere", R)
    with pytest.raises(ValueError, match="image_size"):
        render("tet", R, image_size=0)
    with pytest.raises(ValueError, match="supersample"):
        render("tet", R, supersample=0)
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        render("tet", torch.eye(4))
    with pytest.raises(ValueError, match="not a rotation"):
        render("tet", 2 * R)
    with pytest.raises(ValueError, match="no mark"):
        mark_visible("cube", R)
    with pytest.raises(ValueError, match=r"\(3, 3\)"):
        equivalent_rotations("tet", R[None])


# --------------------------------------------------------------------------------------------------
# Symmetric renders
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", SYMSOL_I_SHAPES)
def test_every_symmetry_renders_the_same_image(shape):
    G = symmetry_group(shape)
    for R in haar(2, seed=1 + SHAPES.index(shape)):
        reference = render(shape, R, image_size=48)
        assert_same_images(render(shape, R @ G, image_size=48), reference)
        other = render(shape, R @ rot_x(25.0), image_size=48)
        assert pixel_diff(other, reference).float().mean() > 3.0
        assert different_pixel_counts(other, reference) > 100


@pytest.mark.parametrize("shape", SYMSOL_I_SHAPES)
def test_unmarked_equivalent_rotations(shape):
    R = haar(3, seed=5)
    sets, counts = equivalent_rotation_sets(shape, R)
    G = symmetry_group(shape)
    assert sets.shape == (3, len(G), 3, 3) and (counts == len(G)).all()
    assert torch.equal(sets[:, 0], R)
    torch.testing.assert_close(sets, R[:, None] @ G[None], rtol=0, atol=1e-12)
    one = equivalent_rotations(shape, R[1].float())
    assert one.dtype == torch.float32 and one.shape == (len(G), 3, 3) and torch.equal(one[0], R[1].float())


# --------------------------------------------------------------------------------------------------
# Marked shapes
# --------------------------------------------------------------------------------------------------


def _dense_mark_samples(shape: str) -> torch.Tensor:
    """Outward unit normals ``(K, 3)`` at dense samples of the mark (ball ``∩`` surface), numpy-built."""
    geom = shape_geometry(shape)
    normals = []
    for part in geom.marks:
        c, rho = part.centre.numpy(), part.radius
        if shape == "tetX":
            v = geom.vertices.numpy()
            far = v[np.argmax(np.linalg.norm(v - c, axis=1))]  # the vertex opposite the marked face
            n = -far / np.linalg.norm(far)
            normals.append(n[None])
        elif shape == "sphereX":
            e1 = np.cross(c, [0.3, 0.5, 0.7])
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(c / np.linalg.norm(c), e1)
            u, w = (a.reshape(-1, 1) for a in np.meshgrid(*(2 * [np.linspace(-1.2 * rho, 1.2 * rho, 301)])))
            pts = c + u * e1 + w * e2  # tangent plane, projected radially onto the sphere
            pts = pts / np.linalg.norm(pts, axis=1, keepdims=True) * SPHERE_RADIUS
            keep = np.linalg.norm(pts - c, axis=1) <= rho
            normals.append(pts[keep] / SPHERE_RADIUS)
        else:
            phi_c = math.atan2(c[2], c[0])
            phi, y = np.meshgrid(np.linspace(-0.6, 0.6, 1201) + phi_c, np.linspace(-rho, rho, 41) + c[1])
            pts = np.stack([CYL_RADIUS * np.cos(phi), y, CYL_RADIUS * np.sin(phi)], -1).reshape(-1, 3)
            keep = np.linalg.norm(pts - c, axis=1) <= rho
            normals.append(np.stack([np.cos(phi), 0 * phi, np.sin(phi)], -1).reshape(-1, 3)[keep])
    return torch.as_tensor(np.concatenate(normals))


def _max_mark_normal_z(shape: str, R: torch.Tensor) -> torch.Tensor:
    """``max`` over the sampled mark of the camera-frame normal's z, ``(...)`` for ``R`` ``(..., 3, 3)``."""
    n = _dense_mark_samples(shape)
    return (R[..., 2, :].to(torch.float64) @ n.T).amax(-1)


def _mark_pixels(images: torch.Tensor) -> torch.Tensor:
    """Number of pixels whose chromaticity is that of the disc or the dot ``(...)``."""
    rgb = images.float()
    total = rgb.sum(-1).clamp_min(1.0)
    chroma = rgb / total[..., None]
    bright = rgb.sum(-1) > 40
    red = chroma[..., 0] > 0.6
    blue = chroma[..., 2] > 0.6
    return (bright & (red | blue)).sum(dim=(-1, -2))


def test_mark_colours_are_distinct_from_the_bodies():
    for shape in SYMSOL_II_SHAPES:
        body = np.array(shape_geometry(shape).colour)
        assert (body / body.sum()).max() < 0.55
    assert np.array(MARK_DISC_COLOUR)[0] / sum(MARK_DISC_COLOUR) > 0.7
    assert np.array(MARK_DOT_COLOUR)[2] / sum(MARK_DOT_COLOUR) > 0.7


@pytest.mark.parametrize("shape", SYMSOL_II_SHAPES)
def test_mark_visibility_matches_samples_labels_and_pixels(shape):
    R = haar(120, seed=20 + SHAPES.index(shape))
    visible = mark_visible(shape, R)
    zmax = _max_mark_normal_z(shape, R)
    clear = zmax.abs() > 0.01
    assert clear.float().mean() > 0.9
    assert torch.equal(visible[clear], zmax[clear] > 0)
    labels = cast_rays(shape, R, 64).label
    has_label = ((labels == LABEL_MARK_DISC) | (labels == LABEL_MARK_DOT)).flatten(1).any(1)
    assert not has_label[~visible].any(), "a hidden mark was rendered"
    pixels = _mark_pixels(render(shape, R, image_size=64))
    assert (pixels[~visible] == 0).all(), "mark-coloured pixels although the mark is hidden"
    well_visible = zmax > 0.3
    assert well_visible.sum() >= 10 and (~visible).sum() >= 10
    assert (pixels[well_visible] > 0).all() and has_label[well_visible].all()


def _clearly_visible(shape: str, n: int, seed: int) -> torch.Tensor:
    R = haar(400, seed=seed)
    centre_normal = shape_geometry(shape).marks[0].normal
    return R[(R[:, 2, :] @ centre_normal) > 0.6][:n]


def _clearly_hidden(shape: str, n: int, seed: int) -> torch.Tensor:
    R = haar(400, seed=seed)
    return R[_max_mark_normal_z(shape, R) < -0.2][:n]


@pytest.mark.parametrize("shape", SYMSOL_II_SHAPES)
def test_visible_mark_has_a_single_equivalent_rotation(shape):
    G = symmetry_group(shape)
    size = 96 if shape == "cylO" else 64  # cylO's nearest symmetries are 1 degree away
    for R in _clearly_visible(shape, 1 if shape == "cylO" else 2, seed=30):
        assert bool(mark_visible(shape, R))
        eq = equivalent_rotations(shape, R)
        assert eq.shape == (1, 3, 3) and torch.equal(eq[0], R)
        reference = render(shape, R, image_size=size)
        counts = different_pixel_counts(render(shape, R @ G[1:], image_size=size), reference)
        assert counts.min() >= 5, f"{shape}: a non-identity group element renders the same image"


@pytest.mark.parametrize("shape", SYMSOL_II_SHAPES)
def test_hidden_mark_equivalent_set(shape):
    G = symmetry_group(shape)
    for R in _clearly_hidden(shape, 2, seed=40):
        eq = equivalent_rotations(shape, R)
        assert eq.shape[0] > 1 and torch.equal(eq[0], R)
        assert_same_images(render(shape, eq, image_size=48), render(shape, R, image_size=48))
        # members are exactly the R @ S with the mark hidden (dense-sample reference, non-grazing S)
        zmax = _max_mark_normal_z(shape, R @ G)  # [G]
        grazing = zmax.abs() < 0.01
        assert grazing.float().mean() < 0.05
        idx, dist = nearest_index(eq, R @ G)
        assert dist.max() < 1e-9 and len(set(idx.tolist())) == len(eq)
        member = torch.zeros(len(G), dtype=torch.bool)
        member[idx] = True
        assert torch.equal(member[~grazing], (zmax <= 0)[~grazing])
        if shape == "tetX":  # 3 rotations per hidden face
            v = shape_geometry(shape).vertices
            hidden_faces = int(((R @ (-v).T)[2] < 0).sum())  # face normals are minus the opposite vertices
            assert len(eq) == 3 * hidden_faces


def test_equivalent_rotation_sets_are_nan_padded():
    R = haar(40, seed=50)
    sets, counts = equivalent_rotation_sets("tetX", R, dtype=torch.float32)
    assert sets.dtype == torch.float32 and sets.shape == (40, int(counts.max()), 3, 3)
    assert (counts == 1).any() and (counts > 1).any()
    for i in range(40):
        one = equivalent_rotations("tetX", R[i])
        torch.testing.assert_close(sets[i, : counts[i]], one.float(), rtol=0, atol=1e-7)
        assert torch.isnan(sets[i, counts[i] :]).all()
        assert torch.equal(sets[i, 0], R[i].float())


# --------------------------------------------------------------------------------------------------
# Renderer against analytic values
# --------------------------------------------------------------------------------------------------


def test_sphere_silhouette_depth_and_normals():
    R = haar(1, seed=60)[0]
    res = 200
    hits = cast_rays("sphereX", R, res)
    radius_px = SPHERE_RADIUS * res / 2
    area = math.pi * radius_px**2
    assert abs(int(hits.hit.sum()) - area) < 0.005 * area
    c = (torch.arange(res, dtype=torch.float64) + 0.5) * 2 / res - 1
    x, y = c[None, :].expand(res, res), -c[:, None].expand(res, res)
    inside = hits.hit
    z = torch.sqrt((SPHERE_RADIUS**2 - x * x - y * y).clamp_min(0))
    torch.testing.assert_close(hits.depth[inside], z[inside], rtol=0, atol=1e-9)
    expected_n = torch.stack([x, y, z], -1) / SPHERE_RADIUS
    torch.testing.assert_close(hits.normal[inside], expected_n[inside], rtol=0, atol=1e-9)
    light = torch.tensor(LIGHT_DIRECTION, dtype=torch.float64)
    shade = AMBIENT + DIFFUSE * (expected_n @ light).clamp_min(0)
    torch.testing.assert_close(hits.shade[inside], shade[inside], rtol=0, atol=1e-9)
    image = render("sphereX", R, image_size=64)
    lit = int((image.amax(-1) > 0).sum())
    area64, perimeter64 = math.pi * (SPHERE_RADIUS * 32) ** 2, 2 * math.pi * SPHERE_RADIUS * 32
    assert area64 - 0.5 * perimeter64 < lit < area64 + perimeter64


def test_face_on_cube_square_and_lambertian_shade():
    eye = torch.eye(3, dtype=torch.float64)
    half = BOUND_RADIUS / math.sqrt(3)
    res = 128
    hits = cast_rays("cube", eye, res)
    side_px = 2 * half * res / 2
    assert abs(int(hits.hit.sum()) - side_px**2) <= 4 * side_px
    normals = hits.normal[hits.hit]
    assert torch.equal(normals, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(len(normals), 3))
    torch.testing.assert_close(hits.depth[hits.hit], torch.full_like(hits.depth[hits.hit], half))
    image = render("cube", eye, image_size=64)
    expected = [round(255 * a * (AMBIENT + DIFFUSE * LIGHT_DIRECTION[2])) for a in shape_geometry("cube").colour]
    centre = image[24:40, 24:40].reshape(-1, 3).int()
    assert (centre - torch.tensor(expected)).abs().max() <= 1
    assert (image[:8] == 0).all() and (image[:, -8:] == 0).all()


def test_cylinder_and_cone_silhouettes():
    eye = torch.eye(3, dtype=torch.float64)
    res = 201  # odd: the centre pixel lies on the axis
    hits = cast_rays("cyl", eye, res)  # side-on: a 2r x 2H rectangle
    w, h = 2 * CYL_RADIUS * res / 2, 2 * CYL_HALF_HEIGHT * res / 2
    assert abs(int(hits.hit.sum()) - w * h) <= 2 * (w + h)
    circle = math.pi * (CONE_BASE_RADIUS * res / 2) ** 2
    for deg, centre_depth in ((90.0, CONE_APEX_HEIGHT), (-90.0, CONE_BASE_DEPTH)):  # apex toward / away
        hits = cast_rays("cone", rot_x(deg), res)
        assert abs(int(hits.hit.sum()) - circle) < 0.01 * circle
        assert abs(float(hits.depth[res // 2, res // 2]) - centre_depth) < 1e-6  # the apex is a double root


def _inside(shape: str, p: torch.Tensor) -> torch.Tensor:
    """Brute-force membership of object-frame points ``(..., 3)`` (from the documented dimensions)."""
    x, y, z = p.unbind(-1)
    if shape in ("cone",):
        k = CONE_BASE_RADIUS / (CONE_APEX_HEIGHT + CONE_BASE_DEPTH)
        return (y <= CONE_APEX_HEIGHT) & (y >= -CONE_BASE_DEPTH) & (x * x + z * z <= (k * (CONE_APEX_HEIGHT - y)) ** 2)
    if shape in ("cyl", "cylO"):
        return (y.abs() <= CYL_HALF_HEIGHT) & (x * x + z * z <= CYL_RADIUS**2)
    if shape == "sphereX":
        return (p * p).sum(-1) <= SPHERE_RADIUS**2
    geom = shape_geometry(shape)
    return ((p @ geom.plane_normals.T) <= geom.plane_offsets).all(-1)


@pytest.mark.parametrize("shape", ["tet", "icosa", "cone", "cyl", "sphereX"])
def test_hits_and_depths_match_brute_force_ray_marching(shape):
    # generic rotations plus views straight along and steeply along the cone / cylinder axis
    R = torch.cat([haar(3, seed=80), torch.stack([rot_x(90.0), rot_x(-90.0), rot_x(80.0), rot_x(-80.0)])])
    res, steps = 32, 801
    hits = cast_rays(shape, R, res)
    c = (torch.arange(res, dtype=torch.float64) + 0.5) * 2 / res - 1
    z = torch.linspace(1.0, -1.0, steps, dtype=torch.float64)  # marching away from the viewer
    p_cam = torch.stack(torch.broadcast_tensors(c[None, :, None], -c[:, None, None], z[None, None, :]), -1)
    for b in range(len(R)):
        inside = _inside(shape, p_cam @ R[b])  # x_obj = R^T x_cam, as row vectors
        brute_hit = inside.any(-1)
        first = torch.where(brute_hit, z[inside.to(torch.int8).argmax(-1)], torch.nan)
        assert (brute_hit & ~hits.hit[b]).sum() == 0
        short = hits.hit[b] & ~brute_hit  # chords shorter than the step: march those rays finely
        if short.any():
            fine = torch.linspace(1.0, -1.0, 200001, dtype=torch.float64)
            xy = torch.stack([c[None, :].expand(res, res)[short], -c[:, None].expand(res, res)[short]], -1)  # [K, 2]
            p_fine = torch.cat(
                [xy[:, None, :].expand(-1, len(fine), 2), fine[None, :, None].expand(len(xy), -1, 1)], -1
            )
            assert _inside(shape, p_fine @ R[b]).any(-1).all()
        both = brute_hit & hits.hit[b]
        assert (hits.depth[b][both] - first[both]).abs().max() <= 2.0 / (steps - 1) + 1e-9


def test_render_is_batch_independent_and_float64_agrees():
    R = haar(6, seed=70)
    for shape in ("icosa", "cylO", "sphereX"):
        batch = render(shape, R, image_size=40)
        single = torch.stack([render(shape, r, image_size=40) for r in R])
        assert torch.equal(batch, single)
        assert torch.equal(render(shape, R.reshape(2, 3, 3, 3), image_size=40), batch.reshape(2, 3, 40, 40, 3))
        assert_same_images(render(shape, R, image_size=40, dtype=torch.float64), batch)
        assert batch.dtype == torch.uint8 and batch.shape == (6, 40, 40, 3)


# --------------------------------------------------------------------------------------------------
# Writer and CLI
# --------------------------------------------------------------------------------------------------

WRITER_ARGS = {"splits": {"train": 6, "test": 3}, "shapes": ("tet", "cylO", "tetX"), "image_size": 32, "seed": 3}


def _snapshot(root) -> dict:
    out = {}
    for dirpath, _, files in os.walk(root):
        for f in files:
            p = os.path.join(dirpath, f)
            with open(p, "rb") as fh:
                out[os.path.relpath(p, root)] = (hashlib.sha256(fh.read()).hexdigest(), os.stat(p).st_mtime_ns)
    return out


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    root = tmp_path_factory.mktemp("symsol") / "set"
    result = render_symsol(root, progress=False, batch_size=4, **WRITER_ARGS)
    return root, result


def test_writer_layout(written):
    root, result = written
    assert not result["cached"] and result["images"] == result["rendered"] == 27
    assert result["images_per_second"] > 0 and result["counts"]["test"] == {"tet": 3, "cylO": 3, "tetX": 3}
    assert sorted(os.listdir(root)) == ["render_info.json", "test", "train"]
    info = json.loads((root / "render_info.json").read_text())
    assert info["format_version"] == render_module.FORMAT_VERSION and info["seed"] == 3
    for split, n in WRITER_ARGS["splits"].items():
        names = sorted(os.listdir(root / split / "images"))
        assert names == sorted(f"{s}_{i:05d}.png" for s in WRITER_ARGS["shapes"] for i in range(n))
        with np.load(root / split / "rotations.npz") as npz:
            assert sorted(npz.files) == sorted(WRITER_ARGS["shapes"])
            arrays = {k: npz[k] for k in npz.files}
        for shape, arr in arrays.items():
            assert arr.dtype == np.float32 and arr.ndim == 4 and arr.shape[0] == n and arr.shape[2:] == (3, 3)
            R = symsol_rotations(n, 3, split, shape)
            np.testing.assert_array_equal(arr[:, 0], R.float().numpy())
            if shape == "tet":
                assert arr.shape[1] == 12 and not np.isnan(arr).any()
            counts = (~np.isnan(arr).all(axis=(2, 3))).sum(1)
            for i in range(n):
                eq = equivalent_rotations(shape, R[i]).float().numpy()
                assert counts[i] == len(eq)
                np.testing.assert_allclose(arr[i, : counts[i]], eq, atol=1e-7)
                assert np.isnan(arr[i, counts[i] :]).all()
            image = np.asarray(Image.open(root / split / "images" / f"{shape}_{n - 1:05d}.png"))
            assert image.shape == (32, 32, 3) and image.dtype == np.uint8
            np.testing.assert_array_equal(image, render(shape, torch.from_numpy(arr[n - 1, 0]), image_size=32).numpy())
    with np.load(root / "train" / "rotations.npz") as npz:
        cylo = npz["cylO"]
    assert np.isnan(cylo).any(), "this seed must give a hidden and a visible cylO mark (padding)"


def test_writer_is_deterministic_and_shapes_are_independent(written, tmp_path):
    root, _ = written
    again = tmp_path / "again"
    render_symsol(again, progress=False, batch_size=5, png_thread=False, **WRITER_ARGS)
    a, b = _snapshot(root), _snapshot(again)
    assert {k: v[0] for k, v in a.items()} == {k: v[0] for k, v in b.items()}
    fewer = tmp_path / "fewer"
    render_symsol(fewer, progress=False, **{**WRITER_ARGS, "shapes": ("tetX",), "splits": {"train": 6}})
    c = _snapshot(fewer)
    for name, (digest, _) in c.items():
        if name.endswith(".png"):
            assert a[name][0] == digest
    with np.load(fewer / "train" / "rotations.npz") as x, np.load(root / "train" / "rotations.npz") as y:
        np.testing.assert_array_equal(x["tetX"], y["tetX"])


def test_writer_cache_hit_and_refusals(written, tmp_path, caplog):
    root, _ = written
    before = _snapshot(root)
    with caplog.at_level("INFO", logger="image2sphere.data.render"):
        result = render_symsol(root, progress=False, **WRITER_ARGS)
    assert result["cached"] and result["rendered"] == 0 and "not re-rendering" in caplog.text
    assert _snapshot(root) == before
    with pytest.raises(FileExistsError, match="different parameters.*choose another directory or delete it"):
        render_symsol(root, progress=False, **{**WRITER_ARGS, "seed": 4})
    with pytest.raises(FileExistsError, match="different parameters"):
        render_symsol(root, progress=False, **{**WRITER_ARGS, "shapes": ("tet",)})
    assert _snapshot(root) == before
    unrelated = tmp_path / "unrelated"
    unrelated.mkdir()
    (unrelated / "notes.txt").write_text("keep me")
    with pytest.raises(FileExistsError, match=str(unrelated)):
        render_symsol(unrelated, progress=False, **WRITER_ARGS)
    assert os.listdir(unrelated) == ["notes.txt"] and (unrelated / "notes.txt").read_text() == "keep me"
    assert sorted(os.listdir(tmp_path)) == ["unrelated"]
    empty = tmp_path / "empty"
    empty.mkdir()
    assert not render_symsol(empty, progress=False, **{**WRITER_ARGS, "splits": {"test": 1}})["cached"]
    assert (empty / "render_info.json").is_file()


def test_writer_leaves_nothing_after_an_exception(tmp_path, monkeypatch):
    calls = []

    def failing_render(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise RuntimeError("boom")
        return render(*args, **kwargs)

    monkeypatch.setattr(render_module, "render", failing_render)
    with pytest.raises(RuntimeError, match="boom"):
        render_symsol(tmp_path / "set", progress=False, batch_size=2, **WRITER_ARGS)
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("other_seed", [3, 4], ids=["same set", "another set"])
def test_writer_uses_the_same_set_completed_by_another_process_meanwhile(tmp_path, monkeypatch, other_seed):
    """Two runs started together on the built-in data both render it: the one that finishes second
    uses the first one's set (the same bytes) instead of failing; a different set there is refused."""
    root = tmp_path / "set"
    other = {**WRITER_ARGS, "seed": other_seed}
    calls = []

    def render_while_another_process_finishes(*args, **kwargs):
        if not calls:  # the other process completes its set while this one renders its first batch
            calls.append(1)
            with monkeypatch.context() as m:  # another process: another pid, so another partial directory
                m.setattr(render_module.os, "getpid", lambda: 1)
                render_symsol(root, progress=False, **other)
        return render(*args, **kwargs)

    monkeypatch.setattr(render_module, "render", render_while_another_process_finishes)
    if other_seed == WRITER_ARGS["seed"]:
        result = render_symsol(root, progress=False, **WRITER_ARGS)
        assert result["cached"] and result["rendered"] == 0
    else:
        with pytest.raises(FileExistsError, match="appeared or changed while rendering"):
            render_symsol(root, progress=False, **WRITER_ARGS)
    assert calls and os.listdir(tmp_path) == ["set"]  # no partial directory left behind
    assert json.loads((root / "render_info.json").read_text())["seed"] == other_seed


def test_writer_argument_validation(tmp_path):
    with pytest.raises(ValueError, match="valid shapes are tet, cube"):
        render_symsol(tmp_path / "a", shapes=("tet", "dodeca"))
    with pytest.raises(ValueError, match="splits"):
        render_symsol(tmp_path / "a", splits={"train": 0})
    with pytest.raises(ValueError, match="image_size"):
        render_symsol(tmp_path / "a", splits={"train": 1}, image_size=0)
    assert os.listdir(tmp_path) == []


def test_cli(tmp_path, capsys):
    root = tmp_path / "cli"
    args = [str(root), "--train", "2", "--test", "1", "--shapes", "cube", "sphereX", "--image-size", "24"]
    assert main([*args, "--no-progress"]) == 0
    assert "images/second" in capsys.readouterr().out
    assert sorted(os.listdir(root / "train" / "images")) == [
        f"{s}_{i:05d}.png" for s in ("cube", "sphereX") for i in (0, 1)
    ]
    assert main([*args, "--no-progress"]) == 0
    assert "already there" in capsys.readouterr().out
    assert main([*args, "--seed", "1", "--no-progress"]) == 1
    assert "delete it" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main([str(tmp_path / "x"), "--shapes", "cube", "dodeca"])
    assert exc.value.code == 2 and "valid shapes are tet cube icosa" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([str(tmp_path / "x"), "--image-size", "0"])
    assert not (tmp_path / "x").exists()

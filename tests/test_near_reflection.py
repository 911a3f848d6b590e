"""Near-field reflections in planar glass (rtsplat.model.mirror and the model's mirrored render)."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from test_raster_hard_cases import surfels_at

from rtsplat.camera import camera_from_fov
from rtsplat.model.checkpoint import read_checkpoint, write_checkpoint
from rtsplat.model.mirror import (
    BEND_MIN_DEGREES,
    FLAT_COLUMNS,
    PLANE_COLUMNS,
    bent_lookup,
    first_plane_hit,
    fit_planes,
    mirror_points,
    mirror_quats,
    move_planes,
    plane_assignment,
    plane_bend,
    plane_parts,
    rotate_vectors,
)
from rtsplat.model.rtmodel import ActiveEffects, RTModel, image_ray_directions
from rtsplat.model.settings import ModelSettings
from rtsplat.model.surfels import init_from_points
from rtsplat.raster import RasterSettings, Surfels, rasterize
from rtsplat.raster.projection import quat_to_rotmat
from rtsplat.train.effects import (
    NEAR_COVERAGE,
    PLANAR_SHARE,
    decide_near_planes,
    planes_seen_edge_on,
    see_through_planes,
)
from rtsplat.train.planes import PlaneRefinement


def plane_row(normal, centre, u, half=(10.0, 10.0), thickness=0.01, dtype=torch.float32, bend=None):
    return torch.tensor([*normal, *centre, *u, *half, thickness, *(bend or [])], dtype=dtype)[None]


# -- geometry ----------------------------------------------------------------------------------------


def test_mirrored_rotation_is_the_reflection_with_one_tangent_axis_flipped():
    g = torch.Generator().manual_seed(3)
    quats = torch.nn.functional.normalize(torch.randn(50, 4, generator=g, dtype=torch.float64), dim=-1)
    normal = torch.nn.functional.normalize(torch.randn(3, generator=g, dtype=torch.float64), dim=0)
    H = torch.eye(3, dtype=torch.float64) - 2.0 * torch.outer(normal, normal)
    flip = torch.diag(torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64))
    mirrored = quat_to_rotmat(mirror_quats(quats, normal))
    torch.testing.assert_close(mirrored, H @ quat_to_rotmat(quats) @ flip, rtol=0, atol=1e-12)
    assert torch.allclose(torch.linalg.det(mirrored), torch.ones(50, dtype=torch.float64))
    # the surfel's normal (third axis) is the reflected normal: a mirror image of the surface
    torch.testing.assert_close(mirrored[..., 2], quat_to_rotmat(quats)[..., 2] @ H.T, rtol=0, atol=1e-12)


def test_mirrored_surfel_appears_where_the_reflected_ray_meets_it():
    # floor mirror z = 0, a bright surfel above it, the camera above too: the mirrored render shows the
    # surfel at the pixel of its mirror image, and the ray through that pixel, reflected at the floor,
    # passes through the surfel
    camera = camera_from_fov((0.0, -3.0, 1.0), (0.0, 0.0, -0.5), width=64, height=48, fov_x_deg=70,
                             dtype=torch.float64)
    normal, centre = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64)
    surfel = surfels_at([[0.3, 0.2, 0.6]], (0.0, -1.0, 0.2), 0.05, dtype=torch.float64)
    mirrored = Surfels(mirror_points(surfel.means, normal, centre), mirror_quats(surfel.quats, normal),
                       surfel.scales, surfel.occupancy, surfel.opacity, surfel.features, surfel.colors)
    out = rasterize(mirrored, camera, backend="reference")
    weight = out.volume_alpha[..., 0]
    row, col = divmod(int(weight.argmax()), camera.width)
    assert weight.max() > 0.5
    direction = image_ray_directions(camera)[row, col]
    origin = camera.center
    t = -origin[2] / direction[2]
    assert t > 0  # the ray goes down to the floor
    hit = origin + t * direction
    reflected = direction - 2.0 * (direction @ normal) * normal
    to_surfel = surfel.means[0] - hit
    miss = (to_surfel - (to_surfel @ reflected) * reflected).norm()
    pixel_size = float((surfel.means[0] - camera.center).norm() / camera.K[0, 0])
    assert miss < 2.0 * pixel_size + 1e-9


def test_plane_assignment_takes_the_first_rectangle_hit_and_misses_parallel_rays():
    camera = camera_from_fov((0.0, -3.0, 0.0), (0.0, 0.0, 0.0), width=16, height=12, dtype=torch.float64)
    directions = image_ray_directions(camera)
    planes = torch.cat([
        plane_row((0, 1, 0), (0, 1, 0), (1, 0, 0), half=(0.2, 0.2), dtype=torch.float64),  # small, far
        plane_row((0, -1, 0), (0, 0, 0), (1, 0, 0), half=(0.5, 0.5), dtype=torch.float64),  # nearer, larger
        plane_row((0, 0, 1), (0, 0, 0), (1, 0, 0), dtype=torch.float64),  # contains the camera's rays at z=0
    ])
    index, distance = plane_assignment(camera, planes, directions)
    centre = index[6, 8]
    assert centre == 1  # the nearer plane wins where both are hit
    assert torch.isfinite(distance[index >= 0]).all() and torch.isinf(distance[index < 0]).all()
    # rays in the plane z = 0 (the camera's own height) never hit the plane z = 0: parallel
    assert not torch.isfinite(torch.tensor(float(distance.min()))) or (index != 2).any()
    grazing = directions[..., 2].abs() < 1e-6
    assert (index[grazing] != 2).all()


# -- fitting -----------------------------------------------------------------------------------------


def _box_points(n=1500, seed=0, noise=0.0):
    g = torch.Generator().manual_seed(seed)
    points, normals = [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            p = torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1
            p[:, axis] = sign
            p += noise * torch.randn(n, 3, generator=g, dtype=torch.float64)
            nrm = torch.zeros(n, 3, dtype=torch.float64)
            nrm[:, axis] = sign
            points.append(p)
            normals.append(nrm)
    return torch.cat(points), torch.cat(normals)


def test_fit_planes_finds_the_faces_of_a_box_and_their_rectangles():
    points, normals = _box_points(noise=0.003)
    planes, shares = fit_planes(points, normals, tolerance=0.02)
    share = float(shares.sum())
    assert planes.shape == (6, PLANE_COLUMNS) and shares.shape == (6,)
    assert share > 0.95
    found = sorted(tuple(int(round(float(x))) for x in row[:3]) for row in planes)
    assert found == sorted([(-1, 0, 0), (1, 0, 0), (0, -1, 0), (0, 1, 0), (0, 0, -1), (0, 0, 1)])
    for row in planes:
        n, c = row[:3], row[3:6]
        assert abs(float(n @ c) - 1.0) < 0.01  # each face lies at distance 1 from the centre
        assert torch.allclose(row[9:11], torch.tensor([1.02, 1.02]), atol=0.03)  # a 2 x 2 face (+ tolerance)


def test_fit_planes_on_a_sphere_explains_too_little_to_switch_near_reflections_on():
    g = torch.Generator().manual_seed(1)
    normals = torch.nn.functional.normalize(torch.randn(6000, 3, generator=g, dtype=torch.float64), dim=-1)
    points = 1.5 * normals
    planes, shares = fit_planes(points, normals, tolerance=0.01 * 3.0 * math.sqrt(3))
    share = float(shares.sum())
    use, why = decide_near_planes("auto", planes.shape[0], share if planes.shape[0] else None)
    assert share < PLANAR_SHARE and not use and "not planar" in why or "no plane" in why
    box_points, box_normals = _box_points()
    planes, shares = fit_planes(box_points, box_normals, tolerance=0.02)
    assert decide_near_planes("auto", planes.shape[0], float(shares.sum()))[0]


def test_decide_near_planes_modes():
    assert decide_near_planes("auto", 2, PLANAR_SHARE)[0]
    assert not decide_near_planes("auto", 2, PLANAR_SHARE - 0.01)[0]
    assert decide_near_planes("on", 2, 0.1)[0]
    assert not decide_near_planes("on", 0, None)[0]
    # glass that reflects little of the model: planar, but its mirrored render covers too little of it
    use, why = decide_near_planes("auto", 2, 0.8, NEAR_COVERAGE - 0.01)
    assert not use and "reflects little" in why
    assert decide_near_planes("auto", 2, 0.8, NEAR_COVERAGE)[0]
    assert decide_near_planes("on", 2, 0.8, 0.0)[0]  # on is on


# -- bent glass --------------------------------------------------------------------------------------

CURVATURE_RADIUS = 1.0  # the test's glass: a ridge z = -y^2 / (2 R) along x (a windshield seen from above)


def _ridge_points(n=4000, half_width=0.3, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, generator=g, dtype=torch.float64) * 2 - 1
    y = (torch.rand(n, generator=g, dtype=torch.float64) * 2 - 1) * half_width
    z = -y * y / (2 * CURVATURE_RADIUS)
    normals = torch.nn.functional.normalize(torch.stack([torch.zeros_like(x), y / CURVATURE_RADIUS,
                                                         torch.ones_like(x)], -1), dim=-1)
    return torch.stack([x, y, z], -1), normals


def test_fit_planes_measures_the_bend_of_curved_glass_and_none_of_flat_glass():
    points, normals = _ridge_points()
    planes, shares = fit_planes(points, normals, tolerance=0.02)
    assert float(shares[0]) > 0.5
    n, _, u, v, _, _ = plane_parts(planes)
    # the height's second derivative across the ridge, in the plane's own axes: -1/R along y
    a, b, c = plane_bend(planes)[0, :3].double()
    hessian = torch.tensor([[2 * a, b], [b, 2 * c]], dtype=torch.float64)
    across = torch.stack([u[0].double() @ torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64),
                          v[0].double() @ torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)])
    along = torch.stack([-across[1], across[0]])
    sign = float(torch.sign(n[0, 2]))  # heights are along the plane's normal
    assert abs(sign * float(across @ hessian @ across) + 1.0 / CURVATURE_RADIUS) < 0.1 / CURVATURE_RADIUS
    assert abs(float(along @ hessian @ along)) < 0.05 / CURVATURE_RADIUS
    box_points, box_normals = _box_points(noise=0.003)
    flat, _ = fit_planes(box_points, box_normals, tolerance=0.02)
    assert flat.shape[0] == 6 and (plane_bend(flat) == 0).all()  # tilts below BEND_MIN_DEGREES are dropped
    assert BEND_MIN_DEGREES > 0


def test_bent_lookup_on_flat_glass_reads_each_pixel_at_itself():
    camera = _camera(width=32, height=24)
    directions = image_ray_directions(camera)
    plane = plane_row((0, 0, 1), (0, 0, 0), (1, 0, 0), half=(1.0, 1.0), dtype=torch.float64,
                      bend=[0.0] * (PLANE_COLUMNS - FLAT_COLUMNS))[0]
    index, distance = plane_assignment(camera, plane[None], directions)
    g = torch.Generator().manual_seed(0)
    content = distance + 3.0 * torch.rand(distance.shape, generator=g, dtype=torch.float64)
    content[::3] = float("inf")  # rows that show nothing
    xy, valid = bent_lookup(camera, directions, plane, distance, content)
    assert valid.sum() == (index >= 0).sum() > 100
    ys, xs = torch.meshgrid(torch.arange(24.0, dtype=torch.float64) + 0.5,
                            torch.arange(32.0, dtype=torch.float64) + 0.5, indexing="ij")
    torch.testing.assert_close(xy[valid], torch.stack([xs, ys], -1)[valid], rtol=0, atol=1e-9)


def _traced_ridge_reflection(camera, target, sigma):
    """Per pixel, the weight of a small disc (facing +z at ``target``, Gaussian of std ``sigma``) seen in
    the ridge mirror by ray tracing: the ray meets the exact surface, reflects about its exact normal and
    crosses the disc's plane."""
    d = image_ray_directions(camera)
    o = camera.center
    # o + t d on z = -y^2 / (2 R): (dy^2 / 2R) t^2 + (dz + oy dy / R) t + (oz + oy^2 / 2R) = 0
    qa = d[..., 1] ** 2 / (2 * CURVATURE_RADIUS)
    qb = d[..., 2] + o[1] * d[..., 1] / CURVATURE_RADIUS
    qc = o[2] + o[1] ** 2 / (2 * CURVATURE_RADIUS)
    disc = qb * qb - 4 * qa * qc
    t = (-qb - torch.sqrt(disc.clamp_min(0))) / (2 * qa)
    x = o + t[..., None] * d
    n = torch.nn.functional.normalize(torch.stack([torch.zeros_like(t), x[..., 1] / CURVATURE_RADIUS,
                                                   torch.ones_like(t)], -1), dim=-1)
    r = d - 2 * (d * n).sum(-1, keepdim=True) * n
    s = (target[2] - x[..., 2]) / r[..., 2]
    crossing = x + s[..., None] * r
    weight = torch.exp(-((crossing - target) ** 2).sum(-1) / (2 * sigma ** 2))
    return torch.where((disc >= 0) & (t > 0) & (s > 0), weight, torch.zeros_like(weight))


def _centroid(weight):
    H, W = weight.shape
    ys, xs = torch.meshgrid(torch.arange(H, dtype=weight.dtype) + 0.5, torch.arange(W, dtype=weight.dtype) + 0.5,
                            indexing="ij")
    return torch.stack([(weight * xs).sum(), (weight * ys).sum()]) / weight.sum()


@pytest.mark.parametrize("target_y", [0.0, 0.4])
def test_a_bent_pane_shows_a_surfel_where_the_curved_glass_reflects_it(target_y):
    """A ridge of glass mirrors a small disc above it: its near reflection lies where ray tracing the
    exact surface puts it (within a pixel); reflected in the flat plane it lies several pixels away."""
    sigma = 0.03
    camera = camera_from_fov((0.0, -2.5, 2.0), (0.0, 0.0, 0.0), width=64, height=48, fov_x_deg=50,
                             dtype=torch.float64)
    target = torch.tensor([0.1, target_y, 0.7], dtype=torch.float64)
    traced = _centroid(_traced_ridge_reflection(camera, target, sigma))
    g = torch.Generator().manual_seed(0)
    surfel = init_from_points(target[None].float(), torch.ones(1, 3), sh_degree=0, occupancy=0.99, opacity=0.99,
                              generator=g, normals=torch.tensor([[0.0, 0.0, 1.0]]))
    with torch.no_grad():
        surfel.log_scales.fill_(math.log(sigma))
    # the ridge's plane z = 0 (u = x, v = y) with the height h = -v^2 / (2 R)
    ridge = plane_row((0, 0, 1), (0, 0, 0), (1, 0, 0), half=(2.0, 2.0), dtype=torch.float64,
                      bend=[0.0, 0.0, -0.5 / CURVATURE_RADIUS, 0.0, 0.0, 0.0])
    found = {}
    for bend in (True, False):
        settings = ModelSettings(env_height=8, env_width=16, env_levels=3, mlp_width=16, sh_degree=0,
                                 near_reflection_bend=bend)
        model = RTModel(surfel, effects=ActiveEffects(near_reflection=True), settings=settings,
                        roi_center=(0.0, 0.0, 0.0), roi_radius=3.0).double()
        model.set_mirror_planes(ridge)
        wanted = torch.ones(camera.height, camera.width, dtype=torch.bool)
        with torch.no_grad():
            _, alpha = model.near_reflection(camera, wanted, None, "reference")
        assert float(alpha.max()) > 0.05
        found[bend] = _centroid(alpha[..., 0])
    assert float((found[True] - traced).norm()) < 1.0
    assert float((found[False] - traced).norm()) > 3.0


# -- the model ---------------------------------------------------------------------------------------


def _model(dtype=torch.float64, near=True, seed=0) -> RTModel:
    """A floor of glass at z = 0 (its plane set as a mirror) under a few coloured surfels above it."""
    g = torch.Generator().manual_seed(seed)
    above = torch.rand(30, 3, generator=g) * torch.tensor([1.6, 1.6, 0.8]) + torch.tensor([-0.8, -0.8, 0.2])
    glass = torch.rand(60, 3, generator=g) * torch.tensor([2.0, 2.0, 0.0]) - torch.tensor([1.0, 1.0, 0.0])
    xyz = torch.cat([above, glass])
    normals = torch.cat([torch.nn.functional.normalize(torch.randn(30, 3, generator=g), dim=-1),
                         torch.tensor([[0.0, 0.0, 1.0]]).expand(60, 3)])
    surfels = init_from_points(xyz, torch.rand(90, 3, generator=g), sh_degree=1, occupancy=0.9, opacity=0.6,
                               generator=g, normals=normals)
    # the mirrored pass trains the reflected surfels here, so that its gradients can be checked
    settings = ModelSettings(env_height=8, env_width=16, env_levels=3, mlp_width=16, sh_degree=1,
                             background_height=8, background_width=16, background_levels=2,
                             near_reflection_trains_surfels=True)
    model = RTModel(surfels, effects=ActiveEffects(near_reflection=near), settings=settings,
                    roi_center=(0.0, 0.0, 0.0), roi_radius=3.0).to(dtype)
    model.set_mirror_planes(plane_row((0, 0, 1), (0, 0, 0), (1, 0, 0), half=(1.0, 1.0), thickness=0.02))
    return model


def _camera(eye=(0.2, -2.5, 1.5), dtype=torch.float64, width=24, height=18):
    return camera_from_fov(eye, (0.0, 0.0, 0.0), width=width, height=height, fov_x_deg=60, dtype=dtype)


def test_near_reflection_changes_only_the_glass_pixels_and_backpropagates_into_the_reflected_surfels():
    model = _model()
    camera = _camera()
    with_near = model.render(camera, stage="full", backend="reference")
    near_alpha = with_near.layers["near_alpha"][..., 0]
    assert near_alpha.max() > 0.3  # the surfels above the floor are seen in it
    index, _ = plane_assignment(camera, model.mirror_planes.double(), image_ray_directions(camera))
    assert (near_alpha[index < 0] == 0).all()  # nothing where the ray misses the pane
    model.set_mirror_planes(torch.zeros(0, PLANE_COLUMNS))
    without = model.render(camera, stage="full", backend="reference")
    changed = (with_near.color - without.color).abs().amax(-1) > 1e-9
    assert changed.any() and not changed[index < 0].any()
    # a surfel above the floor receives gradient through its reflection alone
    model = _model()
    near = model.render(camera, stage="full", backend="reference").layers["near"]
    near.sum().backward()
    above = model.surfels.sh_dc.grad[:30]
    assert above.abs().sum() > 0 and torch.isfinite(model.surfels.means.grad).all()
    assert model.surfels.sh_dc.grad[30:].abs().sum() == 0  # the glass itself is never reflected


def test_a_near_reflection_that_does_not_train_the_surfels_gives_the_same_image_and_no_gradient_to_them():
    camera = _camera()
    reads = _model()
    a = reads.render(camera, stage="full", backend="reference")
    reads.settings = dataclasses.replace(reads.settings, near_reflection_trains_surfels=False)
    b = reads.render(camera, stage="full", backend="reference")
    torch.testing.assert_close(a.color, b.color, rtol=0, atol=0)
    # the surfels' colour reaches the near term through the mirrored render alone (their geometry also
    # through the direct render's clear-glass weight)
    b.layers["near"].sum().backward()
    assert reads.surfels.sh_dc.grad is None or reads.surfels.sh_dc.grad.abs().sum() == 0
    # the rest of the render still trains them
    b = reads.render(camera, stage="full", backend="reference")
    b.color.sum().backward()
    assert reads.surfels.sh_dc.grad[:30].abs().sum() > 0


def test_a_mirrored_pass_with_nothing_to_train_builds_no_autograd_graph():
    """With the surfels only read and the planes fixed, the mirrored render carries no gradient (the rasterizer
    runs no backward for it during training); the same image as with a graph. Trained surfels, or planes that
    are being refined, keep the graph."""
    camera = _camera()
    model = _model()
    wanted = torch.ones(camera.height, camera.width, dtype=torch.bool)
    trained, _ = model.near_reflection(camera, wanted, None, "reference")
    assert trained.requires_grad and trained.grad_fn is not None
    model.settings = dataclasses.replace(model.settings, near_reflection_trains_surfels=False)
    read, read_alpha = model.near_reflection(camera, wanted, None, "reference")
    assert not read.requires_grad and not read_alpha.requires_grad
    torch.testing.assert_close(read, trained.detach(), rtol=0, atol=0)
    planes = model.mirror_planes.clone().requires_grad_(True)
    refined, _ = model.near_reflection(camera, wanted, None, "reference", planes=planes)
    refined.sum().backward()
    assert planes.grad is not None and torch.isfinite(planes.grad).all() and planes.grad.abs().sum() > 0


def test_near_reflection_gradcheck_float64():
    """The mirrored render's colour and coverage against finite differences, with respect to the
    centres, colours and scales of the first surfels above the pane (reference backend, float64)."""
    model = _model()
    camera = _camera(width=16, height=12)
    wanted = torch.ones(camera.height, camera.width, dtype=torch.bool)
    names = ("means", "sh_dc", "log_scales")
    parameters = model.surfels._parameters
    full = {name: parameters[name].detach().clone() for name in names}

    def near_of(*heads):
        originals = {name: parameters[name] for name in names}
        try:
            for name, head in zip(names, heads, strict=True):  # the tensors stand in for the parameters
                parameters[name] = torch.cat([head, full[name][head.shape[0]:]])
            color, alpha = model.near_reflection(camera, wanted, None, "reference")
            return torch.cat([color, alpha], -1)
        finally:
            parameters.update(originals)

    heads = tuple(full[name][:4].clone().requires_grad_(True) for name in names)
    grads = torch.autograd.grad(near_of(*heads).sum(), heads)
    assert all(g.abs().sum() > 0 for g in grads)  # the first surfels are seen in the mirror
    # fast mode: the Jacobian checked along random directions, which any wrong entry would show
    assert torch.autograd.gradcheck(near_of, heads, eps=1e-6, atol=1e-5, rtol=1e-3, fast_mode=True)


@pytest.mark.parametrize("bent", [False, True])
@pytest.mark.parametrize("case", ["camera_in_plane", "grazing", "misses", "behind_camera"])
def test_hard_cases_stay_finite(case, bent):
    model = _model()
    camera = _camera()
    bend = [0.3, -0.1, 0.2, 0.05, 0.0, 0.01] if bent else None
    if case == "camera_in_plane":  # the mirror plane passes through the camera centre
        camera = _camera(eye=(0.2, -2.5, 0.0))
        model.set_mirror_planes(plane_row((0, 0, 1), (0, 0, 0), (1, 0, 0), half=(5.0, 5.0), bend=bend))
    elif case == "grazing":  # the view skims the pane
        camera = _camera(eye=(0.0, -3.0, 1e-3))
        if bent:
            model.set_mirror_planes(plane_row((0, 0, 1), (0, 0, 0), (1, 0, 0), half=(1.0, 1.0), thickness=0.02,
                                              bend=bend))
    elif case == "misses":  # the pane lies outside the view
        model.set_mirror_planes(plane_row((0, 0, 1), (50, 50, 0), (1, 0, 0), half=(0.1, 0.1), bend=bend))
    elif case == "behind_camera":  # the pane is behind the camera
        model.set_mirror_planes(plane_row((0, 1, 0), (0, -4.0, 0), (1, 0, 0), half=(5.0, 5.0), bend=bend))
    result = model.render(camera, stage="full", backend="reference")
    assert torch.isfinite(result.color).all()
    if case in ("camera_in_plane", "misses", "behind_camera"):
        assert result.layers["near_alpha"].abs().max() == 0
    result.color.sum().backward()
    for name, p in model.named_parameters():
        assert p.grad is None or torch.isfinite(p.grad).all(), name


def test_cpu_backend_matches_the_reference_on_the_mirrored_render():
    model = _model(dtype=torch.float64)
    camera = _camera()
    wanted = torch.ones(camera.height, camera.width, dtype=torch.bool)
    ref = model.near_reflection(camera, wanted, RasterSettings(), "reference")
    fast = model.near_reflection(camera, wanted, RasterSettings(), "cpu")
    for a, b in zip(fast, ref, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-8)


def test_mirror_planes_survive_a_checkpoint(tmp_path):
    model = _model(dtype=torch.float32)
    write_checkpoint(tmp_path / "model.pt", model, RasterSettings())
    back = read_checkpoint(tmp_path / "model.pt").build_model("cpu")
    assert back.uses_near_reflection
    torch.testing.assert_close(back.mirror_planes, model.mirror_planes)
    camera = _camera(dtype=torch.float32)
    with torch.no_grad():
        torch.testing.assert_close(back.render(camera, backend="reference").color,
                                   model.render(camera, backend="reference").color)


def test_flat_rows_of_twelve_columns_read_as_unbent_glass_and_moves_keep_the_bend():
    model = _model()
    assert model.mirror_planes.shape == (1, PLANE_COLUMNS) and (plane_bend(model.mirror_planes) == 0).all()
    bend = [0.2, 0.0, -0.1, 0.0, 0.0, 0.0]
    row = plane_row((0, 0, 1), (0, 0, 0), (1, 0, 0), half=(1.0, 1.0), dtype=torch.float64, bend=bend)
    moved = move_planes(row, torch.tensor([[0.1, 0.0, 0.0]], dtype=torch.float64),
                        torch.tensor([0.2], dtype=torch.float64))
    torch.testing.assert_close(plane_bend(moved)[0], torch.tensor(bend, dtype=torch.float64))
    with pytest.raises(ValueError, match="columns"):
        model.set_mirror_planes(torch.zeros(1, 7))


def test_no_near_reflection_effect_renders_no_mirrored_pass():
    model = _model(near=False)
    result = model.render(_camera(), stage="full", backend="reference")
    assert "near" not in result.layers


def test_the_near_weight_output_blends_between_no_near_term_and_the_full_one():
    from rtsplat.model.specular import SpecularNetwork

    torch.manual_seed(0)
    net = SpecularNetwork(8, 4, 16, near_weight=True)
    env, material = torch.randn(5, 8), torch.nn.functional.normalize(torch.randn(5, 4), dim=-1)
    reflectance = torch.rand(5, 1)
    near = (torch.rand(5, 3) * 0.5, torch.rand(5, 1))
    plain, beta = net(env, material, reflectance)
    for logit, expect in ((-40.0, plain), (40.0, reflectance * near[0] + (1 - near[1]) * plain)):
        with torch.no_grad():
            net.mlp[-1].weight[-1].zero_()
            net.mlp[-1].bias[-1] = logit
        blended, beta_near = net(env, material, reflectance, near=near)
        torch.testing.assert_close(blended, expect)
        torch.testing.assert_close(beta_near, beta)  # the weight is its own output: beta is untouched


def test_a_plane_is_glass_only_if_what_its_rays_show_lies_behind_it():
    # a pane at y = 0 and, off to the side, a floor at z = -1, each met first by its own rays from a camera
    # at y = -3: the pane's rays show the scene 2 units behind it, the floor's show the floor itself
    f64 = dict(dtype=torch.float64)
    pane = plane_row((0, -1, 0), (0, 0, 0), (1, 0, 0), half=(1.0, 1.0), thickness=0.02, **f64)
    floor = plane_row((0, 0, 1), (5, 3, -1), (1, 0, 0), half=(5.0, 3.0), thickness=0.02, **f64)
    planes = torch.cat([pane, floor])
    origin = torch.tensor([0.0, -3.0, 0.0], **f64).expand(50, 3)
    g = torch.Generator().manual_seed(0)
    through_pane = torch.nn.functional.normalize(
        torch.tensor([0.0, 1.0, 0.0], **f64) + 0.1 * torch.randn(50, 3, generator=g, **f64), dim=-1)
    to_floor = torch.nn.functional.normalize(torch.tensor([[1.0, 1.2, -0.2]], **f64), dim=-1).expand(50, 3)
    index, distance = first_plane_hit(torch.cat([origin, origin]), torch.cat([through_pane, to_floor]), planes)
    assert index[:50].eq(0).all() and index[50:].eq(1).all()
    rays = torch.cat([
        torch.cat([origin, through_pane, (distance[:50] + 2.0)[:, None]], -1),
        torch.cat([origin, to_floor, distance[50:, None]], -1),
    ])
    assert see_through_planes(planes, rays).tolist() == [True, False]
    assert see_through_planes(planes[:0], rays).shape == (0,)


def test_a_plane_fitted_to_a_silhouette_cone_is_seen_edge_on_from_its_apex():
    # a strip of a cone (apex: a marked camera at y = -4, looking at the origin, half-angle 15 degrees), as
    # the faces of a visual hull are, against a pane at y = 0 seen from in front of it
    f64 = dict(dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    apex = torch.tensor([0.0, -4.0, 0.0], **f64)
    azimuth = math.radians(20.0) * (2 * torch.rand(3000, generator=g, **f64) - 1)
    along = 3.5 + torch.rand(3000, generator=g, **f64)
    half = math.radians(15.0)
    ring = torch.stack([torch.cos(azimuth), torch.zeros_like(azimuth), torch.sin(azimuth)], -1)
    axis = torch.tensor([0.0, 1.0, 0.0], **f64)
    points = apex + along[:, None] * (math.cos(half) * axis + math.sin(half) * ring)
    normals = math.cos(half) * ring - math.sin(half) * axis
    planes, shares = fit_planes(points, normals, tolerance=0.02)
    assert planes.shape[0] >= 1 and float(shares.sum()) > 0.5
    assert planes_seen_edge_on(planes, apex[None]).all()
    assert not planes_seen_edge_on(planes, torch.tensor([[0.0, 4.0, 0.0], [3.0, -3.0, 2.0]], **f64)).any()
    pane = plane_row((0, -1, 0), (0, 0, 0), (1, 0, 0), half=(1.0, 1.0), thickness=0.02, **f64)
    in_front = torch.tensor([[0.0, -3.0, 0.0], [2.0, -3.0, 1.0]], **f64)
    assert not planes_seen_edge_on(pane, in_front).any()
    assert planes_seen_edge_on(pane, torch.cat([in_front, torch.tensor([[3.0, 0.1, 0.0]], **f64)])).all()
    assert planes_seen_edge_on(pane, in_front[:0]).tolist() == [False]


def test_near_reflection_on_surface_keeps_the_pixels_whose_surface_is_the_pane():
    """A surfel standing in front of the pane hides it: with ``near_reflection_on_surface`` its pixels get no
    reflection, the pane's own pixels keep theirs, and the image does not change where the surface is the pane."""
    from rtsplat.model.rtmodel import on_plane_surface

    camera = _camera()
    model = _model()
    model.settings = dataclasses.replace(model.settings, near_reflection_on_surface=False)
    everywhere = model.render(camera, stage="full", backend="reference")
    model.settings = dataclasses.replace(model.settings, near_reflection_on_surface=True)
    on_surface = model.render(camera, stage="full", backend="reference")
    directions = image_ray_directions(camera)
    index, distance = plane_assignment(camera, model.mirror_planes.double(), directions)
    thickness = plane_parts(model.mirror_planes)[5]
    on = on_plane_surface(index, distance, directions, camera, everywhere.layers["depth"][..., 0], thickness)
    hit = index >= 0
    assert on.any() and (hit & ~on).any()  # pane pixels, and pixels whose ray meets the pane behind a surfel
    assert (on_surface.layers["near_alpha"][..., 0][~on] == 0).all()
    assert on_surface.layers["near_alpha"][..., 0][on].max() > 0.3
    torch.testing.assert_close(on_surface.color[on], everywhere.color[on])
    assert not on[~hit].any()


# -- mirror planes refined against the images ----------------------------------------------------------


def _skew(w):
    zero = torch.zeros_like(w[0])
    return torch.stack([torch.stack([zero, -w[2], w[1]]), torch.stack([w[2], zero, -w[0]]),
                        torch.stack([-w[1], w[0], zero])])


def test_rotate_vectors_is_the_matrix_exponential_and_smooth_at_zero():
    g = torch.Generator().manual_seed(5)
    vectors = torch.randn(40, 3, generator=g, dtype=torch.float64)
    sizes = torch.logspace(-9, 0.5, 40, dtype=torch.float64)[:, None]  # through the series' switch at 1e-4
    rotation = torch.randn(40, 3, generator=g, dtype=torch.float64) * sizes
    expected = torch.stack([torch.linalg.matrix_exp(_skew(w)) @ v for w, v in zip(rotation, vectors, strict=True)])
    torch.testing.assert_close(rotate_vectors(vectors, rotation), expected, rtol=0, atol=1e-11)
    # the derivative at zero is the cross product, finite and exact
    zero = torch.zeros(40, 3, dtype=torch.float64, requires_grad=True)
    (rotate_vectors(vectors, zero) * vectors.roll(1, 0)).sum().backward()
    torch.testing.assert_close(zero.grad, torch.cross(vectors, vectors.roll(1, 0), dim=-1), rtol=0, atol=1e-12)
    assert torch.autograd.gradcheck(lambda w: rotate_vectors(vectors[:6], w),
                                     (torch.full((6, 3), 1e-5, dtype=torch.float64, requires_grad=True),))


def test_move_planes_turns_the_rectangle_about_its_centre_and_shifts_along_the_new_normal():
    planes = torch.cat([plane_row((0, 0, 1), (0.5, -0.2, 0.1), (1, 0, 0), half=(1.0, 0.5), thickness=0.02,
                                  dtype=torch.float64),
                        plane_row((1, 0, 0), (2.0, 0.0, 0.0), (0, 1, 0), half=(0.3, 0.4), thickness=0.05,
                                  dtype=torch.float64)])
    assert torch.equal(move_planes(planes, torch.zeros(2, 3, dtype=torch.float64), torch.zeros(2, dtype=torch.float64)),
                       planes)
    angle = math.radians(3.0)
    moved = move_planes(planes, torch.tensor([[angle, 0.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64),
                        torch.tensor([0.0, 0.25], dtype=torch.float64))
    n, c, u, v, half, thickness = plane_parts(moved)
    n0, c0, u0, *_ = plane_parts(planes)
    assert math.isclose(math.degrees(math.acos(float(n[0] @ n0[0]))), 3.0, rel_tol=1e-9)
    torch.testing.assert_close(u[0], u0[0], rtol=0, atol=1e-15)  # the rotation axis is the rectangle's u
    torch.testing.assert_close(c[0], c0[0], rtol=0, atol=0)  # about its centre
    torch.testing.assert_close(c[1], c0[1] + 0.25 * n0[1], rtol=0, atol=1e-15)
    torch.testing.assert_close(torch.stack([n.norm(dim=-1), u.norm(dim=-1)]), torch.ones(2, 2, dtype=torch.float64))
    assert float((n * u).sum(-1).abs().max()) < 1e-15
    torch.testing.assert_close(half, plane_parts(planes)[4], rtol=0, atol=0)
    torch.testing.assert_close(thickness, plane_parts(planes)[5], rtol=0, atol=0)


def _mirror_only_model(dtype=torch.float64) -> RTModel:
    """The surfels above the glass floor of :func:`_model` without the glass itself: what a pane mirrors."""
    model = _model(dtype=dtype)
    keep = torch.arange(30)
    from rtsplat.model.surfels import SurfelParameters

    model.surfels = SurfelParameters({k: v.detach()[keep].clone() for k, v in model.surfels.tensors().items()})
    return model


def test_near_reflection_gradcheck_with_respect_to_the_plane_motion():
    model = _mirror_only_model()
    camera = _camera(width=16, height=12)
    wanted = torch.ones(camera.height, camera.width, dtype=torch.bool)
    base = model.mirror_planes.double()

    def near_of(rotation, shift):
        color, alpha = model.near_reflection(camera, wanted, None, "reference",
                                             planes=move_planes(base, rotation, shift))
        return torch.cat([color, alpha], -1)

    motion = (torch.tensor([[0.01, -0.02, 0.0]], dtype=torch.float64, requires_grad=True),
              torch.tensor([0.01], dtype=torch.float64, requires_grad=True))
    grads = torch.autograd.grad(near_of(*motion).sum(), motion)
    assert all(g.abs().sum() > 0 for g in grads)
    assert torch.autograd.gradcheck(near_of, motion, eps=1e-6, atol=1e-5, rtol=1e-3)
    # the cpu backend's backward gives the same plane gradient
    fast = torch.autograd.grad(torch.cat(model.near_reflection(camera, wanted, None, "cpu",
                                                               planes=move_planes(base, *motion)), -1).sum(), motion)
    for a, b in zip(fast, grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-8)


def test_plane_refinement_finds_the_pane_that_made_the_reflections():
    """The near reflections of a pane at z = 0 seen from three views; a refinement started 4 degrees and
    5 cm off (the error of the fitted planes on the synthetic cabin) moves the plane back towards it with
    the model fixed."""
    model = _mirror_only_model()
    true = model.mirror_planes.double()
    cameras = [_camera(eye=eye, width=24, height=18) for eye in ((0.2, -2.5, 1.5), (1.8, -1.2, 1.2), (-1.5, -1.8, 1.8))]
    wanted = torch.ones(18, 24, dtype=torch.bool)
    with torch.no_grad():
        targets = [torch.cat(model.near_reflection(c, wanted, None, "cpu", planes=true), -1) for c in cameras]
    start = move_planes(true, torch.tensor([[math.radians(4.0), 0.0, 0.0]], dtype=torch.float64),
                        torch.tensor([0.05], dtype=torch.float64))
    refinement = PlaneRefinement(start, extent=1.0, lr_rotation=2e-3, lr_shift=2e-3)

    def errors(planes):
        n, c, *_ = plane_parts(planes)
        angle = math.degrees(math.acos(min(1.0, float(n[0] @ true[0, :3]))))
        return angle, abs(float((c[0] - true[0, 3:6]) @ true[0, :3]))

    angle0, shift0 = errors(start)
    for step in range(150):
        camera, target = cameras[step % 3], targets[step % 3]
        near = torch.cat(model.near_reflection(camera, wanted, None, "cpu", planes=refinement.planes()), -1)
        ((near - target) ** 2).sum().backward()
        refinement.step()
    angle, shift = errors(refinement.current)
    assert angle < 0.3 * angle0 and shift < 0.3 * shift0, (angle0, shift0, angle, shift)
    moved = refinement.moved()[0]
    assert moved["degrees"] > 0 and torch.isfinite(refinement.current).all()


def test_plane_refinement_drops_a_non_finite_step_and_leaves_a_plane_without_gradient_in_place():
    planes = torch.cat([plane_row((0, 0, 1), (0, 0, 0), (1, 0, 0), dtype=torch.float64),
                        plane_row((1, 0, 0), (1, 0, 0), (0, 1, 0), dtype=torch.float64)])
    refinement = PlaneRefinement(planes, extent=2.0, lr_rotation=1e-2, lr_shift=1e-2)
    rows = refinement.planes()
    (rows[0, :6].sum() * float("nan")).backward()  # a NaN loss reaches the first plane only
    after = refinement.step()
    assert torch.isfinite(after).all()
    torch.testing.assert_close(after, planes, rtol=0, atol=0)
    refinement = PlaneRefinement(planes, extent=2.0, lr_rotation=1e-2, lr_shift=1e-2)
    (refinement.planes()[0, 3:6] @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)).backward()
    after = refinement.step()  # Adam's first step: the learning rate, times the extent for the shift
    assert math.isclose(float(after[0, 5]), -2e-2, rel_tol=1e-6)
    torch.testing.assert_close(after[0, :3], planes[0, :3], rtol=0, atol=0)  # lowering it turns nothing
    torch.testing.assert_close(after[1], planes[1], rtol=0, atol=0)  # no gradient: unmoved

"""The true see-through surfaces of the synthetic scenes, and the normal error measured against them."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from rtsplat.bench.glass_normals import normal_errors
from rtsplat.model.surfels import point_cloud_normals
from rtsplat.synth.scenes import CabinParams, DomeParams, FilmParams, params_from_dict, see_through_samples


def test_see_through_samples_lie_on_each_scenes_glass_with_unit_normals():
    dome = DomeParams()
    p, n = see_through_samples("dome", dome, spacing=0.05)
    centre = np.array([0.0, 0.0, dome.dome_center_z])
    assert len(p) > 1000 and (p[:, 2] > 0).all()
    np.testing.assert_allclose(np.linalg.norm(p - centre, axis=1), dome.dome_radius, atol=1e-9)
    np.testing.assert_allclose(n, (p - centre) / dome.dome_radius, atol=1e-9)

    cabin = CabinParams()
    p, n = see_through_samples("cabin", cabin, spacing=0.05)
    on_x = np.isclose(np.abs(p[:, 0]), cabin.half_length) & (np.abs(p[:, 1]) <= cabin.half_width + 1e-9)
    on_y = np.isclose(np.abs(p[:, 1]), cabin.half_width) & (np.abs(p[:, 0]) <= cabin.half_length + 1e-9)
    assert (on_x | on_y).all() and on_x.any() and on_y.any()
    np.testing.assert_allclose(np.abs(n[on_x & ~on_y, 0]), 1.0, atol=1e-9)  # the corners lie on two panes
    np.testing.assert_allclose(np.abs(n[on_y & ~on_x, 1]), 1.0, atol=1e-9)
    top = cabin.body_height + cabin.window_height
    assert p[:, 2].min() < cabin.body_height + 0.02 and p[:, 2].max() > top - 0.02

    film = FilmParams()
    p, n = see_through_samples("film", film, spacing=0.05)
    R = film.curvature_radius
    np.testing.assert_allclose(p[:, 0] ** 2 + (p[:, 1] - R) ** 2, R * R, rtol=1e-9)
    np.testing.assert_allclose(n, (p - [0.0, R, 0.0]) * [1, 1, 0] / R, atol=1e-9)  # off the axis, at -y: the cameras
    assert (n[:, 1] < 0).all()
    assert see_through_samples("opaque")[0].shape == (0, 3)


def test_params_from_dict_reads_the_scene_json_form():
    cabin = params_from_dict("cabin", {"half_length": 1.0, "content": {"object_size": [0.1, 0.2], "n_objects": 2}})
    assert cabin.half_length == 1.0 and cabin.content.object_size == (0.1, 0.2) and cabin.content.n_objects == 2
    with pytest.raises(ValueError, match="unknown scene"):
        params_from_dict("nowhere", {})


def test_normal_errors_measure_the_tilt_of_the_normals_on_the_glass_only():
    glass, normals = see_through_samples("dome", DomeParams(), spacing=0.05)
    pick = np.random.default_rng(0).choice(len(glass), 400, replace=False)
    points = glass[pick]
    axis = np.cross(normals[pick], [0.3, 0.5, 0.8])
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = math.radians(10.0)  # each normal turned 10 degrees about an axis in the tangent plane
    tilted = normals[pick] * math.cos(angle) + np.cross(axis, normals[pick]) * math.sin(angle)
    tilted[::2] *= -1  # either side of the glass
    far = points * 1.5  # not on the glass: ignored
    errors = normal_errors(np.concatenate([points, far]), np.concatenate([tilted, tilted]), glass, normals,
                           tolerance=0.05)
    assert errors.on_glass == 400
    assert abs(errors.median - 10.0) < 1.0 and abs(errors.weighted_median - 10.0) < 1.0 and errors.p90 < 12.0
    weights = np.where(np.arange(400) < 100, 1.0, 1e-6)
    upright = tilted.copy()
    upright[:100] = normals[pick][:100]  # the heavy quarter is exact
    assert normal_errors(points, upright, glass, normals, 0.05, weights).weighted_median < 1.0
    assert normal_errors(far, tilted, glass, normals, 0.05) is None


def test_point_cloud_normals_are_the_surfaces_normals_up_to_sign():
    g = torch.Generator().manual_seed(0)
    uv = torch.rand(2000, 2, generator=g, dtype=torch.float64) * 2 - 1
    normal = torch.nn.functional.normalize(torch.tensor([0.2, -0.4, 1.0], dtype=torch.float64), dim=0)
    e1 = torch.nn.functional.normalize(torch.linalg.cross(normal, torch.tensor([1.0, 0, 0]).double()), dim=0)
    e2 = torch.linalg.cross(normal, e1)
    plane = uv[:, :1] * e1 + uv[:, 1:] * e2 + 0.002 * torch.randn(2000, 1, generator=g, dtype=torch.float64) * normal
    n = point_cloud_normals(plane, chunk=512)
    assert float((n @ normal).abs().min()) > math.cos(math.radians(5.0))
    sphere = torch.nn.functional.normalize(torch.randn(3000, 3, generator=g, dtype=torch.float64), dim=1)
    n = point_cloud_normals(sphere)
    assert float((n * sphere).sum(1).abs().median()) > math.cos(math.radians(3.0))
    assert point_cloud_normals(torch.zeros(2, 3)).tolist() == [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]


def test_family_see_through_samples_lie_on_the_members_glass():
    from rtsplat.synth import family

    p, n = family.see_through_samples("family/shop_window-0", spacing=0.1)
    params = family.draw_params(family.parse_name("shop_window-0"))
    assert len(p) > 100
    np.testing.assert_allclose(p[:, 1], 0.0, atol=1e-5)  # the pane lies in the facade's plane y = 0
    np.testing.assert_allclose(np.abs(n[:, 1]), 1.0, atol=1e-6)
    assert p[:, 2].min() >= params["sill"] - 1e-5 and p[:, 2].max() <= params["sill"] + params["pane_height"] + 1e-5
    assert p[:, 2].max() - p[:, 2].min() > 0.8 * params["pane_height"]  # spread over the pane, not one spot

    p, n = family.see_through_samples("family/curved-1", spacing=0.05)
    params = family.draw_params(family.parse_name("curved-1"))
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
    assert params["section"] == "sphere"
    # a spherical cap: every sample at the sphere's radius from one centre, its normal along the radius
    centre = np.linalg.lstsq(np.c_[2 * p, np.ones(len(p))], (p**2).sum(1), rcond=None)[0][:3]
    radial = p - centre
    np.testing.assert_allclose(np.linalg.norm(radial, axis=1), params["radius"], rtol=5e-3)  # flat facets
    cosines = np.abs((radial / np.linalg.norm(radial, axis=1, keepdims=True) * n).sum(1))
    assert np.median(cosines) > 0.999  # the mesh's vertex normals are the sphere's

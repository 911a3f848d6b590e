"""rtsplat.bench.reflection_reach: which glass pixels reflect something near, on scenes whose answer is known
in closed form (a vertical pane, a floor below it)."""

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")


def _scene(floor_x: tuple[float, float] | None):
    """A vertical glass pane in the plane x = 0 (1 x 1 m around (0, 0, 1)) and, unless None, a floor z = 0 over
    x in ``floor_x``, |y| < 20."""
    from rtsplat.synth.render import load_scene, set_variant

    set_variant()

    def transform(matrix):
        return mi.ScalarTransform4f(np.asarray(matrix, dtype=np.float64).tolist())

    # Mitsuba's rectangle spans [-1, 1]^2 in its xy plane with normal +z
    pane = np.array([[0, 0, 1, 0], [0.5, 0, 0, 0], [0, 0.5, 0, 1.0], [0, 0, 0, 1]], dtype=np.float64)
    elements = {"pane": {"type": "rectangle", "to_world": transform(pane),
                         "bsdf": {"type": "thindielectric", "int_ior": 1.5, "ext_ior": 1.0}}}
    if floor_x is not None:
        lo, hi = floor_x
        floor = np.diag([(hi - lo) / 2, 20.0, 1.0, 1.0])
        floor[0, 3] = (hi + lo) / 2
        elements["floor"] = {"type": "rectangle", "to_world": transform(floor), "bsdf": {"type": "diffuse"}}
    return load_scene(elements, [], spp=1)


def _camera():
    import torch

    from rtsplat.camera import camera_from_fov

    return camera_from_fov((3.0, 0.4, 3.0), (0.0, 0.0, 1.0), width=40, height=30, fov_x_deg=30.0, dtype=torch.float64)


def _floor_hits(camera, mask):
    """Closed form, per mask pixel (row-major): where the pixel's ray, mirrored in the pane x = 0, meets
    z = 0 (x there), and how far from the pane."""
    from rtsplat.synth.cameras import pixel_rays

    rows, cols = np.nonzero(mask)
    origin, directions = pixel_rays(camera, cols + 0.5, rows + 0.5)
    on_pane = origin + (-origin[0] / directions[:, 0])[:, None] * directions
    mirrored = directions * np.array([-1.0, 1.0, 1.0])
    distance = -on_pane[:, 2] / mirrored[:, 2]
    return on_pane[:, 0] + distance * mirrored[:, 0], distance


def test_a_pane_seen_from_above_reflects_the_floor_at_the_distance_the_mirror_geometry_gives():
    from rtsplat.bench.reflection_reach import reflection_reach
    from rtsplat.synth.render import first_hit_mask

    scene, camera = _scene(floor_x=(-20.0, 20.0)), _camera()
    mask = first_hit_mask(scene, camera)
    assert mask.sum() > 50  # the pane fills part of the view
    reach = reflection_reach(scene, [camera], [mask])
    assert reach.glass_pixels == mask.sum()
    # every ray comes down onto the pane, so its mirror image goes down too and meets the floor
    assert reach.near_pixels == reach.glass_pixels and reach.near_weight == pytest.approx(1.0)
    _, distance = _floor_hits(camera, mask)
    assert reach.median_distance == pytest.approx(float(np.median(distance)), rel=1e-3)
    # without the floor nothing is near
    empty = reflection_reach(_scene(floor_x=None), [camera], [mask])
    assert empty.glass_pixels == mask.sum() and empty.near_pixels == 0 and np.isnan(empty.median_distance)


def test_a_floor_patch_near_the_pane_catches_the_pixels_the_closed_form_sends_there_and_weights_count_them():
    from rtsplat.bench.reflection_reach import reflection_reach
    from rtsplat.synth.render import first_hit_mask

    scene, camera = _scene(floor_x=(0.0, 1.5)), _camera()
    mask = first_hit_mask(scene, camera)
    x, _ = _floor_hits(camera, mask)
    expected = (x > 0.0) & (x < 1.5)
    assert 0.2 < expected.mean() < 0.8  # the patch catches some of the reflections, not all
    reach = reflection_reach(scene, [camera], [mask])
    assert abs(reach.near_pixels - int(expected.sum())) <= 0.01 * mask.sum()
    # weights on the pixels the patch catches: all of the weight is near; on the others: none of it
    caught = np.zeros(mask.shape)
    caught[mask] = expected
    assert reflection_reach(scene, [camera], [mask], [caught]).near_weight > 0.98
    assert reflection_reach(scene, [camera], [mask], [(1.0 - caught) * mask]).near_weight < 0.02
    assert reflection_reach(scene, [camera], [mask], stride=2).glass_pixels == mask[::2, ::2].sum()

"""Ray casting through the Mitsuba scenes of the synthetic-scene tests (plain module, imported by the test files)."""

from __future__ import annotations

import numpy as np


def interior_hits(scene, cams) -> tuple[int, int]:
    """Over every pixel-centre ray of the cameras ``cams`` (:mod:`rtsplat.synth.cameras`) into the loaded Mitsuba
    ``scene``: how many rays first hit an interior object (a shape whose id starts with ``object_``), and how many
    first hit see-through glass and then an interior object behind it."""
    import mitsuba as mi

    from rtsplat.synth.cameras import pixel_rays
    from rtsplat.synth.render import is_see_through, see_through_flags

    glass = see_through_flags()
    bare = through = 0
    for cam in cams:
        jj, ii = np.mgrid[0:int(cam.height), 0:int(cam.width)]
        o, d = pixel_rays(cam, ii.ravel() + 0.5, jj.ravel() + 0.5)
        for dk in d.tolist():
            ray = mi.Ray3f(mi.Point3f(*o.tolist()), mi.Vector3f(*dk))
            si = scene.ray_intersect(ray)
            if not si.is_valid():
                continue
            bare += si.shape.id().startswith("object_")
            if is_see_through(si, glass):  # (Mitsuba merges a scene's panes into one unnamed mesh)
                behind = scene.ray_intersect(si.spawn_ray(ray.d))
                through += behind.is_valid() and behind.shape.id().startswith("object_")
    return bare, through

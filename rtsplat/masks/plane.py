"""Marks on flat glass carried through the glass's plane, for marked views that all look from one side.

A visual hull needs marked views from around the object; views from one side (a walk past a shop window)
leave its depth unbounded. Flat glass is bounded by its plane instead. The plane is fitted to the SfM points
on the glass's outline (:func:`outline_points`): points just outside a marked view's mask (its frame, the
wall or mullions around it), within ``plane_band`` of the view's longest side, and not well inside any mark
(points seen through the glass or in its reflection). Among those, points seen through the glass beside it
or a floor below it may form planes too, so RANSAC proposes a few distinct planes (:func:`ransac_planes`)
and the one on which the marks agree best is kept (:func:`mark_agreement`: each marked view's mask cast onto
the plane and seen from each other marked view, against that view's mask where the first view's frame reaches,
as mean IoU). Of planes the marks agree on about as well the one that holds the most points is kept: marks
that span the frame along a walk agree through every plane that contains the walk's direction.

A plane that passes in front of more than :data:`MAX_IN_FRONT` of the SfM points the marked views see inside their
marks is not the glass (:func:`in_front_share`): what is seen through glass, or reflected in it, lies behind it;
its agreement counts :data:`REFINE_PENALTY` times that excess less. Where few SfM points lie on the glass's own
outline (a thin frame) no proposed plane may be the glass's; then the best one is moved to where the marks agree
best (:func:`refine_plane`), and the plane is refused when they still agree at under :data:`MIN_AGREEMENT`
(:func:`check_agreement`; marks of several panes may agree through their panes' planes instead,
:mod:`rtsplat.masks.panes`).

Every view then gets the marks cast onto the plane (:func:`cast_marks`): its pixels' rays meet the plane, and
a pixel is inside when most of the marked views that have its plane point in frame see it inside their masks;
with occluders (SfM points on a surface) the pixels where those lie clearly in front of the plane are left out.
The result is refined to the image's edges as a projected hull is (:mod:`rtsplat.masks.propagation`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsplat.io.colmap import ColmapView
from rtsplat.masks.propagation import _dilate, _iou, _occluded, _resize_mask, opaque_depth, project_points

MIN_INLIERS = 12  # a plane on fewer outline points is not trusted
AGREEMENT_TIE = 0.02  # planes whose marks' agreement differs by less are told apart by their points
MIN_AGREEMENT = 0.85  # marks agreeing less on their best plane (mean IoU between marked views) are refused
MAX_IN_FRONT = 0.2  # a plane with more of the points seen inside the marks in front of it is not the glass
RANSAC_ITERATIONS = 400
RANSAC_TOLERANCE = 0.01  # inlier distance as a fraction of the outline points' median depth
CANDIDATES = 6  # distinct planes proposed by RANSAC
DISTINCT_DEGREES = 5.0  # planes whose normals differ by less (and that lie close together) are the same
REFINE_BELOW = 0.95  # the best proposed plane, refined on the marks' agreement when they agree less through it
REFINE_EVALUATIONS = 80  # of the marks' agreement while refining a plane
REFINE_PENALTY = 5.0  # agreement lost per share of the points seen through the glass in front of the plane
INSIDE_MARGIN = 3  # pixels: an SfM point this far inside a mark is seen through the glass, not on its outline


@dataclass
class GlassPlane:
    """The glass's plane ``normal . x + offset = 0`` (unit normal facing the marked cameras) and its fit."""

    normal: np.ndarray
    offset: float
    residual: float  # RMS distance of its inliers to the plane (scene units)
    relative_residual: float  # the residual over the outline points' median distance from the marked cameras
    inliers: int
    outline_points: int  # SfM points on the marks' outlines it was fitted among
    agreement: float  # the marks' mean IoU between marked views through the plane (mark_agreement)
    refined: bool = False  # moved from the best proposed plane to where the marks agree best (refine_plane)

    def record(self) -> dict:
        """The plane as the masks summary records it."""
        return {"normal": [round(float(x), 6) for x in self.normal], "offset": round(float(self.offset), 6),
                "residual": float(self.residual), "relative_residual": float(self.relative_residual),
                "inliers": self.inliers, "outline_points": self.outline_points,
                "agreement": round(float(self.agreement), 4), "refined": self.refined}


class PlaneFitError(ValueError):
    """No plane fits the marks; the message says why."""


# ----------------------------------------------------------------------------------------------
# the fit


def fit_plane(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane (unit normal, offset) through ``points`` [N, 3] (N >= 3)."""
    centre = points.mean(0)
    normal = np.linalg.svd(points - centre, full_matrices=False)[2][-1]
    return normal, float(-normal @ centre)


def ransac_planes(points: np.ndarray, tolerance: float, rng: np.random.Generator,
                  count: int = CANDIDATES) -> list[tuple[np.ndarray, float, np.ndarray]]:
    """Up to ``count`` distinct planes (unit normal, offset, inlier bool [N]) proposed by RANSAC, most inliers
    first: planes through three random points, ranked by how many points lie within ``tolerance``, each kept
    when it differs from those kept before (normals :data:`DISTINCT_DEGREES` apart, or offsets 3 ``tolerance``
    apart at the points' centre) and refitted to its inliers by least squares; planes of fewer than
    :data:`MIN_INLIERS` points are not proposed. The planes may share points: the glass's plane meets a floor
    or a wall along its edge."""
    if len(points) < MIN_INLIERS:
        return []
    samples = rng.integers(0, len(points), (RANSAC_ITERATIONS, 3))
    a, b, c = (points[samples[:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    norms = np.linalg.norm(normals, axis=1)
    ok = norms > 1e-12 * max(1.0, float(np.abs(points).max()) ** 2)
    normals, a = normals[ok] / norms[ok, None], a[ok]
    support = (np.abs(points @ normals.T - np.einsum("ij,ij->i", normals, a)) < tolerance).sum(0)
    centre = points.mean(0)
    planes: list[tuple[np.ndarray, float, np.ndarray]] = []
    for k in np.argsort(-support, kind="stable"):
        if support[k] < MIN_INLIERS or len(planes) == count:
            break
        normal, offset = normals[k], float(-normals[k] @ a[k])
        inliers = np.abs(points @ normal + offset) < tolerance
        for _ in range(2):  # refit to the inliers, then take the inliers of the refitted plane
            normal, offset = fit_plane(points[inliers])
            inliers = np.abs(points @ normal + offset) < tolerance
            if inliers.sum() < MIN_INLIERS:
                break
        if inliers.sum() < MIN_INLIERS or any(_same_plane(normal, offset, n, o, centre, tolerance)
                                              for n, o, _ in planes):
            continue
        planes.append((normal, offset, inliers))
    return planes


def _same_plane(n1: np.ndarray, o1: float, n2: np.ndarray, o2: float, centre: np.ndarray, tolerance: float) -> bool:
    """Whether two planes are the same up to :data:`DISTINCT_DEGREES` and 3 ``tolerance`` at ``centre``."""
    cos = float(n1 @ n2)
    if abs(cos) < np.cos(np.radians(DISTINCT_DEGREES)):
        return False
    sign = 1.0 if cos > 0 else -1.0
    return abs((n1 @ centre + o1) - sign * (n2 @ centre + o2)) < 3 * tolerance


def seen_through(xyz: np.ndarray, marked: list[tuple[ColmapView, np.ndarray]]) -> list[tuple[ColmapView, np.ndarray]]:
    """Per marked view, the SfM points ``xyz`` it sees :data:`INSIDE_MARGIN` pixels inside its mask: what lies
    behind the glass or is reflected in it (a reflection triangulates behind the glass too)."""
    seen = []
    for view, mask in marked:
        ok, u, v = _in_frame(view, xyz, mask.shape)
        deep = ~_dilate(~mask, INSIDE_MARGIN)
        ok[ok] = deep[v[ok], u[ok]]
        seen.append((view, xyz[ok]))
    return seen


def in_front_share(normal: np.ndarray, offset: float, seen: list[tuple[ColmapView, np.ndarray]],
                   tolerance: float) -> float:
    """The share of the points seen inside the marks (:func:`seen_through`) that lie more than ``tolerance`` on
    the marked camera's side of the plane: points the glass would have to hide (0 with none)."""
    front, total = 0, 0
    for view, points in seen:
        side = np.sign(normal @ view.center + offset)
        front += int((side * (points @ normal + offset) > tolerance).sum())
        total += len(points)
    return front / total if total else 0.0


def outline_points(xyz: np.ndarray, marked: list[tuple[ColmapView, np.ndarray]], band: float,
                   within: list[tuple[ColmapView, np.ndarray]] | None = None) -> np.ndarray:
    """The SfM points ``xyz`` on the marks' outlines: in front of a marked view within ``band`` of its longest
    side just outside its mask, and not :data:`INSIDE_MARGIN` pixels inside any marked view's mask (nor inside
    any mask of ``within``: every mark, for the outline of one of its panes)."""
    near = np.zeros(len(xyz), bool)
    inside = np.zeros(len(xyz), bool)
    for view, mask in marked:
        seen, u, v = _in_frame(view, xyz, mask.shape)
        ring = _dilate(mask, max(2, int(round(band * max(mask.shape))))) & ~mask
        near[seen] |= ring[v[seen], u[seen]]
    for view, mask in marked + (within or []):
        seen, u, v = _in_frame(view, xyz, mask.shape)
        deep = ~_dilate(~mask, INSIDE_MARGIN)
        inside[seen] |= deep[v[seen], u[seen]]
    return xyz[near & ~inside]


def _in_frame(view: ColmapView, xyz: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Whether each point is in front of ``view`` and inside its frame of ``shape``, and its pixel (column, row)."""
    uv, _, front = project_points(view, xyz)
    h, w = shape
    u, v = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    return front & (u >= 0) & (u < w) & (v >= 0) & (v < h), u, v


# ----------------------------------------------------------------------------------------------
# casting


def pixel_rays(view: ColmapView, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """World directions [h, w, 3] (not normalised; unit depth along the view's axis) of the pixel centres of
    ``view`` at ``scale`` of its size, and its centre; distortion undone through pycolmap."""
    h, w = int(round(view.height * scale)), int(round(view.width * scale))
    u, v = np.meshgrid((np.arange(w) + 0.5) / scale, (np.arange(h) + 0.5) / scale)
    uv = np.stack([u.ravel(), v.ravel()], -1)
    if view.has_distortion:
        import pycolmap

        camera = pycolmap.Camera.create_from_model_name(1, view.model, 1.0, view.width, view.height)
        camera.params = view.params.tolist()
        xy = np.asarray(camera.cam_from_img(np.ascontiguousarray(uv)), dtype=np.float64)[:, :2]
    else:
        K = view.K
        xy = (uv - K[:2, 2]) / np.diag(K)[:2]
    rays = np.concatenate([xy, np.ones((len(xy), 1))], 1) @ view.world_to_camera[:3, :3]
    return rays.reshape(h, w, 3), view.center


def plane_points(plane: GlassPlane, view: ColmapView, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Where the rays of ``view``'s pixels (at ``scale``) meet the plane: points [h, w, 3] and their depth along
    the view's axis [h, w] (inf where a ray runs parallel to the plane or meets it behind the camera)."""
    rays, centre = pixel_rays(view, scale)
    towards = rays @ plane.normal
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = -(plane.normal @ centre + plane.offset) / towards
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.inf)
    points = centre + rays * np.where(np.isfinite(depth), depth, 0.0)[..., None]
    return points, depth


def _mark_votes(points: np.ndarray, marked: list[tuple[ColmapView, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """[views, N] bool: whether each marked view has each point in frame, and whether it sees it in its mask."""
    seen = np.zeros((len(marked), len(points)), bool)
    inside = np.zeros((len(marked), len(points)), bool)
    for k, (view, mask) in enumerate(marked):
        uv, _, front = project_points(view, points)
        front &= np.isfinite(uv).all(1)
        uv[~front] = -1.0
        u, v = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        h, w = mask.shape
        seen[k] = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        inside[k, seen[k]] = mask[v[seen[k]], u[seen[k]]]
    return seen, inside


def cast_marks(plane: GlassPlane, marked: list[tuple[ColmapView, np.ndarray]], view: ColmapView,
               scale: float = 1.0, occluders: np.ndarray | None = None) -> np.ndarray:
    """The marks cast through the plane into ``view`` (bool, its size times ``scale``): a pixel whose ray meets
    the plane in front of the camera is inside when at least half the marked views that have that point in frame
    see it in their masks; with ``occluders`` (SfM points) the pixels where those lie clearly in front of the
    plane are left out."""
    points, depth = plane_points(plane, view, scale)
    hit = np.isfinite(depth).ravel()
    seen, inside = _mark_votes(points.reshape(-1, 3)[hit], marked)
    votes = seen.sum(0)
    out = np.zeros(depth.size, bool)
    out[hit] = (votes > 0) & (2 * inside.sum(0) >= votes)
    out = out.reshape(depth.shape)
    if occluders is None or not len(occluders) or not out.any():
        return out
    step = RANSAC_TOLERANCE * float(np.median(depth[out]))
    return out & ~_occluded(opaque_depth(view, occluders, scale), depth, step)


def mark_agreement(plane: GlassPlane, marked: list[tuple[ColmapView, np.ndarray]], scale: float) -> float:
    """How well the marks agree through ``plane``: each marked view's mask cast into each other marked view (at
    ``scale``), against that view's mask on the pixels whose plane point the first view has in frame and on those
    whose ray misses the plane (behind the camera, or parallel to it), as IoU; the mean over the pairs where either
    is non-empty (0 when none is)."""
    scores = []
    for i, (view, mask) in enumerate(marked):
        points, depth = plane_points(plane, view, scale)
        truth = _resize_mask(mask, *depth.shape[::-1])
        hit = np.isfinite(depth).ravel()
        for j, other in enumerate(marked):
            if i == j:
                continue
            seen, inside = _mark_votes(points.reshape(-1, 3)[hit], [other])
            frame = np.zeros(depth.size, bool)
            frame[hit] = seen[0]
            cast = np.zeros(depth.size, bool)
            cast[hit] = inside[0]
            judged = frame.reshape(depth.shape) | ~np.isfinite(depth)  # a mark off the plane is a miss
            if (truth & judged).any() or cast.any():
                scores.append(_iou(cast.reshape(depth.shape), truth & judged))
    return float(np.mean(scores)) if scores else 0.0


def facing_planes(outline: np.ndarray, centres: np.ndarray, tolerance: float,
                  seed: int = 0) -> list[tuple[np.ndarray, float]]:
    """The planes :func:`ransac_planes` proposes through the ``outline`` points, each oriented so that the marked
    cameras at ``centres`` lie on its positive side; a plane that passes between those cameras is left out."""
    facing = []
    for normal, offset, _ in ransac_planes(outline, tolerance, np.random.default_rng(seed)):
        sign = 1.0 if float(np.median(centres @ normal + offset)) >= 0 else -1.0
        normal, offset = sign * normal, sign * offset
        if not np.any(centres @ normal + offset <= 0):
            facing.append((normal, offset))
    return facing


def in_front_penalty(share: float) -> float:
    """The agreement a plane loses for the ``share`` of what the marks see through the glass in front of it:
    :data:`REFINE_PENALTY` times the share beyond :data:`MAX_IN_FRONT`."""
    return REFINE_PENALTY * max(0.0, share - MAX_IN_FRONT)


def _plane_score(normal: np.ndarray, offset: float, marked: list[tuple[ColmapView, np.ndarray]], scale: float,
                 behind: list[tuple[ColmapView, np.ndarray]], tolerance: float) -> tuple[float, float]:
    """(the marks' agreement through the plane, the share of what they see through the glass in front of it)."""
    plane = GlassPlane(normal, offset, 0.0, 0.0, 0, 0, 0.0)
    return mark_agreement(plane, marked, scale), in_front_share(normal, offset, behind, tolerance)


def refine_plane(normal: np.ndarray, offset: float, marked: list[tuple[ColmapView, np.ndarray]], scale: float,
                 behind: list[tuple[ColmapView, np.ndarray]], tolerance: float) -> tuple[np.ndarray, float]:
    """The plane near (``normal``, ``offset``) on which the marks agree best (Nelder-Mead over its normal's two
    angles and its offset, :data:`REFINE_EVALUATIONS` evaluations), a plane in front of more than
    :data:`MAX_IN_FRONT` of what the marked views see through the glass counting as a disagreement."""
    from scipy.optimize import minimize

    centres = np.stack([v.center for v, _ in marked])

    def plane_of(x: np.ndarray) -> tuple[np.ndarray, float]:
        return np.array([np.sin(x[0]) * np.cos(x[1]), np.sin(x[0]) * np.sin(x[1]), np.cos(x[0])]), float(x[2])

    def loss(x: np.ndarray) -> float:
        n, d = plane_of(x)
        if np.any(centres @ n + d <= 0):
            return 1.0
        agreement, share = _plane_score(n, d, marked, scale, behind, tolerance)
        return -agreement + in_front_penalty(share)

    x0 = np.array([np.arccos(np.clip(normal[2], -1.0, 1.0)), np.arctan2(normal[1], normal[0]), offset])
    simplex = np.stack([x0, x0 + [0.15, 0, 0], x0 + [0, 0.15, 0], x0 + [0, 0, 10 * tolerance]])
    result = minimize(loss, x0, method="Nelder-Mead",
                      options={"maxfev": REFINE_EVALUATIONS, "initial_simplex": simplex})
    return plane_of(result.x if result.fun < loss(x0) else x0)


def _fit(outline: np.ndarray, normal: np.ndarray, offset: float, depth: float, tolerance: float) -> GlassPlane:
    """The plane with its fit to the outline points within ``tolerance`` of it (their RMS distance)."""
    distances = np.abs(outline @ normal + offset)
    near = distances[distances < tolerance]
    rms = float(np.sqrt(np.mean(near**2))) if len(near) else 0.0
    return GlassPlane(normal, offset, rms, rms / depth, len(near), len(outline), 0.0)


def glass_plane(xyz: np.ndarray, marked: list[tuple[ColmapView, np.ndarray]], band: float, scale: float,
                seed: int = 0, refine: bool = True, agree: bool = True) -> GlassPlane:
    """The plane of the glass the marks outline (see the module's description; ``refine``: whether the best
    proposed plane may be moved to where the marks agree); :class:`PlaneFitError` saying why when too few SfM
    points lie on the outlines, every proposed plane passes between the marked cameras, or (``agree``) the marks
    agree on none (:func:`check_agreement`)."""
    outline = outline_points(xyz, marked, band)
    if len(outline) < MIN_INLIERS:
        raise PlaneFitError(f"{len(outline)} SfM point(s) lie on the marks' outlines (at least {MIN_INLIERS} "
                            "are needed to fit the glass's plane)")
    centres = np.stack([v.center for v, _ in marked])
    depth = float(np.median(np.linalg.norm(outline[:, None] - centres[None], axis=2)))
    tolerance = RANSAC_TOLERANCE * depth
    behind = seen_through(xyz, marked)
    best, best_score = None, -np.inf
    for normal, offset in facing_planes(outline, centres, tolerance, seed):
        agreement, share = _plane_score(normal, offset, marked, scale, behind, 3 * tolerance)
        score = agreement - in_front_penalty(share)
        if score > best_score + AGREEMENT_TIE:  # ties keep the plane of more points
            best, best_score = (normal, offset), score
    if best is None:
        raise PlaneFitError(f"no plane that passes in front of the marked cameras holds {MIN_INLIERS} of the "
                            f"{len(outline)} SfM points on the marks' outlines")
    refined = refine and best_score < REFINE_BELOW
    if refined:  # few points on the glass's own outline: the marks place the plane
        best = refine_plane(*best, marked, scale, behind, 3 * tolerance)
    plane = _fit(outline, *best, depth, tolerance)
    plane.agreement, share = _plane_score(plane.normal, plane.offset, marked, scale, behind, 3 * tolerance)
    plane.refined = refined
    if share > MAX_IN_FRONT:
        raise PlaneFitError(f"every plane the marks agree on passes in front of what the marked views see through "
                            f"the glass ({share:.0%} of those points, at most {MAX_IN_FRONT:.0%} may lie in front)")
    if agree:
        check_agreement(plane.agreement)
    return plane


def check_agreement(agreement: float, best: float | None = None) -> None:
    """:class:`PlaneFitError` when the marks agree at under :data:`MIN_AGREEMENT` (mean IoU between marked views
    through their plane, or ``best`` through their panes' planes)."""
    if max(agreement, best or 0.0) < MIN_AGREEMENT:
        raise PlaneFitError(f"the marks agree on no plane through the SfM points on their outlines (best mean IoU "
                            f"between marked views {max(agreement, best or 0.0):.2f}, at least {MIN_AGREEMENT} is "
                            "needed)")

"""Marks made of several panes, each carried through its own plane.

A mark may outline several separate pieces of glass (a car's side window and, at the walk's end, its end window
around the corner); these are not in one plane. Each connected piece of a marked view's mask is a piece of a pane
(:func:`mark_pieces`); pieces of different marked views are the same pane when the marks' single plane
(:func:`rtsplat.masks.plane.glass_plane`) carries one onto the other (:func:`match_pieces`). Marks that form one pane
keep the single plane. Otherwise each pane gets the plane on which it is most consistent (:func:`pane_plane`), among
the single plane and those RANSAC proposes through the SfM points on its own outline: its pieces' agreement from
view to view (when more than one marked view holds it), and its consistency with the other marked views, those
that see the plane from the pane's side: the share of the pane cast into them that lands inside their marks (a
plane that carries the pane where another view marked nothing is not its plane). A plane in front of more than
:data:`rtsplat.masks.plane.MAX_IN_FRONT` of the points seen through the pane loses as for the single plane. Of
planes about as consistent (within :data:`rtsplat.masks.plane.AGREEMENT_TIE`) the one on which most of the pane's
outline points lie is kept, the single plane on a tie: a pane that only one marked view holds, where no other
marked view sees its plane, is placed by its outline alone. A pane with fewer than
:data:`rtsplat.masks.plane.MIN_INLIERS` SfM points on its outline keeps the single plane.

Marks that agree too little through the single plane (:func:`rtsplat.masks.plane.check_agreement`) are taken when
they agree through their panes' planes. A view's mask is the union of every pane cast through its plane into it
(:func:`cast_panes`); a pane with its own plane reaches only the views on the side of its plane its marked views
look from."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsplat.io.colmap import ColmapView
from rtsplat.masks.plane import (
    AGREEMENT_TIE,
    MIN_INLIERS,
    RANSAC_TOLERANCE,
    GlassPlane,
    _fit,
    cast_marks,
    check_agreement,
    facing_planes,
    in_front_penalty,
    in_front_share,
    mark_agreement,
    outline_points,
    seen_through,
)
from rtsplat.masks.propagation import _resize_mask

MATCH_OVERLAP = 0.5  # pieces overlapping by this share of the smaller one, through the single plane, are one pane

Marked = list[tuple[ColmapView, np.ndarray]]


@dataclass
class Pane:
    """One pane of the marks: its piece in each marked view that holds one, and the plane it is carried through
    (``own``: fitted to its own outline; else the marks' single plane)."""

    marked: Marked
    plane: GlassPlane
    own: bool = False

    def record(self) -> dict:
        """The pane as the masks summary records it."""
        record = {"views": [v.name for v, _ in self.marked], "own_plane": self.own, **self.plane.record()}
        if len(self.marked) == 1:  # no other marked view to agree with
            del record["agreement"]
        return record


def mark_pieces(mask: np.ndarray) -> list[np.ndarray]:
    """The connected pieces (8-connected) of a mask, largest first."""
    import cv2

    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    order = sorted(range(1, count), key=lambda k: -stats[k, cv2.CC_STAT_AREA])
    return [labels == k for k in order]


def match_pieces(plane: GlassPlane, marked: Marked, scale: float) -> list[Marked]:
    """The marked views' pieces grouped into panes: two pieces of different views are one pane when ``plane`` casts
    either onto the other with an overlap of :data:`MATCH_OVERLAP` of the smaller (at ``scale``), and groups are
    joined through shared pieces. Each pane lists its pieces by view (pieces of one view in a pane joined)."""
    pieces = [(k, view, piece) for k, (view, mask) in enumerate(marked) for piece in mark_pieces(mask)]
    parent = list(range(len(pieces)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, (k, view, piece) in enumerate(pieces):
        for j, (other_k, other, other_piece) in enumerate(pieces):
            if other_k == k or root(i) == root(j):
                continue
            cast = cast_marks(plane, [(view, piece)], other, scale)
            target = _resize_mask(other_piece, *cast.shape[::-1])
            smaller = min(int(cast.sum()), int(target.sum()))
            if smaller and (cast & target).sum() >= MATCH_OVERLAP * smaller:
                parent[root(j)] = root(i)
    panes: dict[int, dict[int, np.ndarray]] = {}
    for i, (k, _, piece) in enumerate(pieces):
        by_view = panes.setdefault(root(i), {})
        by_view[k] = by_view[k] | piece if k in by_view else piece
    return [[(marked[k][0], piece) for k, piece in sorted(by_view.items())] for by_view in panes.values()]


def _front_side(normal: np.ndarray, offset: float, views: Marked, view: ColmapView) -> bool:
    """Whether ``view`` looks at the plane from the side of ``views``' cameras."""
    side = np.sign(np.median([normal @ v.center + offset for v, _ in views]))
    return bool(side * (normal @ view.center + offset) > 0)


def consistency(plane: GlassPlane, pane: Marked, others: Marked, scale: float) -> float | None:
    """The share of ``pane`` cast through ``plane`` into the ``others`` (marked views without a piece of it, on
    the side of the plane ``pane``'s views look from) that lands inside their marks; None when it lands in none."""
    inside, total = 0, 0
    for view, mask in others:
        if not _front_side(plane.normal, plane.offset, pane, view):
            continue
        cast = cast_marks(plane, pane, view, scale)
        total += int(cast.sum())
        inside += int((cast & _resize_mask(mask, *cast.shape[::-1])).sum())
    return inside / total if total else None


def _pane_score(plane: GlassPlane, pane: Marked, others: Marked, scale: float, behind: Marked,
                tolerance: float) -> float:
    """The pane's agreement between its views (with two or more) and its consistency with the other marked views
    (:func:`consistency`), averaged; less :func:`rtsplat.masks.plane.in_front_penalty` of the share of what is seen
    through it in front of the plane."""
    terms = [mark_agreement(plane, pane, scale)] if len(pane) > 1 else []
    consistent = consistency(plane, pane, others, scale)
    if consistent is not None:
        terms.append(consistent)
    score = float(np.mean(terms)) if terms else 1.0
    return score - in_front_penalty(in_front_share(plane.normal, plane.offset, behind, tolerance))


def pane_plane(xyz: np.ndarray, pane: Marked, marked: Marked, single: GlassPlane, band: float, scale: float,
               seed: int = 0) -> Pane:
    """The pane's :class:`Pane`: the plane it is most consistent on (see the module's description) among the
    marks' ``single`` plane and the planes RANSAC proposes through the SfM points on its outline."""
    outline = outline_points(xyz, pane, band, within=marked)
    if len(outline) < MIN_INLIERS:
        return Pane(pane, single)
    names = {v.name for v, _ in pane}
    others = [(v, m) for v, m in marked if v.name not in names]
    centres = np.stack([v.center for v, _ in pane])
    depth = float(np.median(np.linalg.norm(outline[:, None] - centres[None], axis=2)))
    tolerance = RANSAC_TOLERANCE * depth
    behind = seen_through(xyz, pane)
    candidates = [(single.normal, single.offset), *facing_planes(outline, centres, tolerance, seed)]
    scores = [_pane_score(GlassPlane(n, o, 0.0, 0.0, 0, 0, 0.0), pane, others, scale, behind, 3 * tolerance)
              for n, o in candidates]
    support = [int((np.abs(outline @ n + o) < tolerance).sum()) for n, o in candidates]
    tied = [k for k, score in enumerate(scores) if score >= max(scores) - AGREEMENT_TIE]
    chosen = max(tied, key=lambda k: (support[k], -k))  # of planes about as consistent, the one of most points
    if chosen == 0:
        return Pane(pane, single)
    plane = _fit(outline, *candidates[chosen], depth, tolerance)
    plane.agreement = mark_agreement(plane, pane, scale) if len(pane) > 1 else 0.0
    return Pane(pane, plane, own=True)


def glass_panes(xyz: np.ndarray, marked: Marked, single: GlassPlane, band: float, scale: float) -> list[Pane]:
    """The marks' panes (:func:`match_pieces` through the ``single`` plane), each with its plane
    (:func:`pane_plane`); one pane on the single plane when the marks form one.
    :class:`rtsplat.masks.plane.PlaneFitError` when the marks agree neither through the single plane nor through
    the panes' planes (the agreement of each pane that more than one marked view holds, weighted by its marked
    pixels; :func:`rtsplat.masks.plane.check_agreement`)."""
    panes = match_pieces(single, marked, scale)
    if len(panes) == 1:
        check_agreement(single.agreement)
        return [Pane(marked, single)]
    fitted = [pane_plane(xyz, pane, marked, single, band, scale) for pane in panes]
    held = [p for p in fitted if len(p.marked) > 1]
    if held:  # the panes' agreement, each weighted by its marked pixels
        agreements = [p.plane.agreement if p.own else mark_agreement(single, p.marked, scale) for p in held]
        pixels = [sum(int(piece.sum()) for _, piece in p.marked) for p in held]
        check_agreement(single.agreement, float(np.average(agreements, weights=pixels)))
    else:
        check_agreement(single.agreement)
    return fitted


def cast_panes(panes: list[Pane], marked: Marked, view: ColmapView, scale: float = 1.0,
               occluders: np.ndarray | None = None) -> np.ndarray:
    """The marks of the ``marked`` views cast into ``view`` (bool, its size times ``scale``): the union of each
    pane's pieces in those views cast through its plane (:func:`rtsplat.masks.plane.cast_marks`); a pane on its own
    plane only into a view on the side of the plane its marked views look from."""
    names = {v.name for v, _ in marked}
    out = np.zeros((int(round(view.height * scale)), int(round(view.width * scale))), bool)
    for pane in panes:
        pieces = [(v, piece) for v, piece in pane.marked if v.name in names]
        if not pieces or (pane.own and not _front_side(pane.plane.normal, pane.plane.offset, pane.marked, view)):
            continue
        out |= cast_marks(pane.plane, pieces, view, scale, occluders)
    return out


def panes_text(panes: list[Pane]) -> str:
    """What the stage prints of the panes: nothing for one pane, else each pane's views, plane and residual."""
    if len(panes) < 2:
        return ""
    parts = []
    for pane in panes:
        views = ", ".join(v.name for v, _ in pane.marked)
        if pane.own:
            agree = f", its views agree through it at IoU {pane.plane.agreement:.2f}" if len(pane.marked) > 1 else ""
            parts.append(f"{views}: its own plane, {pane.plane.inliers} of {pane.plane.outline_points} SfM points "
                         f"on its outline, RMS residual {pane.plane.relative_residual:.2%}{agree}")
        else:
            parts.append(f"{views}: the marks' plane")
    return f"; {len(panes)} panes ({'; '.join(parts)})"

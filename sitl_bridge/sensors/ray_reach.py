"""Which lidar rays could hit anything: a cheap bounding-box test before pybullet casts them.

pybullet's `rayTestBatch` costs about 2 us per ray, most of a scan, while in open air most rays
of a scan hit nothing. A ray that cannot reach any body's bounding box (grown by
`REACH_MARGIN_M`) nor the ground plane has pybullet's no-hit answer (fraction 1, no body)
without being cast; only the others are cast, one by one as in a full batch, so a scan is the
same bit for bit (`Lidar.prune`; tests/test_lidar.py compares it with the full cast). A ray never
sees the body it starts in (bullet reports no ray leaving a convex shape), so each vehicle's
own box is left out of its rays' test.
"""

from __future__ import annotations

import numpy as np

from sitl_bridge.jit import dual, kernel

REACH_MARGIN_M = 0.1
"""Bounding boxes and the ground are grown by this much: a ray passing closer is cast (the
test only has to be conservative; pybullet's boxes already include the collision margins)."""


@kernel()
def rays_that_may_hit(starts: np.ndarray, ends: np.ndarray, owners: np.ndarray, boxes: np.ndarray,
                      box_owners: np.ndarray, ground: bool, margin: float) -> np.ndarray:
    """Per ray (segment `starts[r]` to `ends[r]`, cast by vehicle `owners[r]`): whether it may
    hit the ground plane z = 0 (when `ground`) or a box of `boxes` (rows min xyz, max xyz) not
    owned by its vehicle (`box_owners`, -1: an obstacle), all grown by `margin`. A ray with a
    non-finite end is always cast."""
    n = starts.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    for r in range(n):
        s0, s1, s2 = starts[r, 0], starts[r, 1], starts[r, 2]
        d0, d1, d2 = ends[r, 0] - s0, ends[r, 1] - s1, ends[r, 2] - s2
        if not (np.isfinite(s0) and np.isfinite(s1) and np.isfinite(s2)
                and np.isfinite(d0) and np.isfinite(d1) and np.isfinite(d2)):
            out[r] = True
            continue
        if ground and min(s2, s2 + d2) <= margin:
            out[r] = True
            continue
        for b in range(boxes.shape[0]):
            if box_owners[b] >= 0 and box_owners[b] == owners[r]:
                continue
            if _segment_meets_box(s0, s1, s2, d0, d1, d2, boxes[b], margin):
                out[r] = True
                break
    return out


@dual
def _segment_meets_box(s0: float, s1: float, s2: float, d0: float, d1: float, d2: float, box: np.ndarray,
                       margin: float) -> bool:
    """Slab test: whether the segment s + t d, t in [0, 1], meets the box grown by `margin`."""
    t_in, t_out = 0.0, 1.0
    for axis in range(3):
        s = s0 if axis == 0 else s1 if axis == 1 else s2
        d = d0 if axis == 0 else d1 if axis == 1 else d2
        lo, hi = box[axis] - margin, box[axis + 3] + margin
        if abs(d) < 1e-12:
            if s < lo or s > hi:
                return False
            continue
        a, b = (lo - s) / d, (hi - s) / d
        if a > b:
            a, b = b, a
        t_in, t_out = max(t_in, a), min(t_out, b)
        if t_in > t_out:
            return False
    return True


@kernel()
def rays_to_cast(starts: np.ndarray, ends: np.ndarray, owners: np.ndarray, boxes: np.ndarray, box_owners: np.ndarray,
                 ground: bool, margin: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`rays_that_may_hit` as (indices of the rays to cast, their starts, their ends)."""
    cast = np.flatnonzero(rays_that_may_hit(starts, ends, owners, boxes, box_owners, ground, margin))
    return cast, starts[cast], ends[cast]


@kernel()
def merge_hits(count: int, cast: np.ndarray, fractions: np.ndarray, bodies: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per ray of `count`: the hit fraction and body of the cast ones (`cast`, in order), the
    no-hit answer (1, body -1) for the others."""
    all_fractions = np.ones(count)
    all_bodies = np.full(count, -1, dtype=np.int64)
    for k in range(cast.shape[0]):
        all_fractions[cast[k]] = fractions[k]
        all_bodies[cast[k]] = bodies[k]
    return all_fractions, all_bodies


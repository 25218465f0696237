"""The rays the fit looks at: every fired ray of the board's rings (and one more on each side)
within its azimuth window, from all scans, with their board coordinates at a pose."""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from align.board import BoardSpec
from align.fit.label_kernels import pool_rows, window_pool, window_rays
from align.geometry import rotation, unwrap
from align.params import RaysParams
from align.search.result import Segmentation
from twin.core.scan import Scan

#: Labels: a hit on the board, a miss (no return, or one far behind), unknown (a return in front:
#: an occluder), and a dropout (no return where the board's own dropouts show that no return
#: does not mean no board: a dark square of a printed pattern).
HIT, MISS, UNKNOWN, DROPOUT = 1, 0, -1, -2


@dataclass
class Rays:
    """The candidate rays of all scans, in one set."""

    origin: np.ndarray  # (M, 3) m, {L}
    direction: np.ndarray  # (M, 3)
    distance: np.ndarray  # (M,) m, 0 = no return
    laser: np.ndarray  # (M,)
    azimuth: np.ndarray  # (M,) rad, unwrapped around the board
    ring: np.ndarray
    gidx: np.ndarray  # index into the concatenation of the scans
    scan: np.ndarray  # which scan


def candidates_at(scans: list[Scan], segs: list[Segmentation], theta: np.ndarray,
                  board: BoardSpec, *, p: RaysParams
                  ) -> tuple[Rays, tuple[np.ndarray, ...], float]:
    """Every fired ray (hit or not) near the board's rectangle, from all scans, with their
    board coordinates (X, Z, lam) at ``theta`` and the rings' spacing on the board there
    (`_ring_spacing`, m): the fit's next steps need both at the same pose. A ray's coordinates
    do not depend on which others are computed with it."""
    cat = _candidate_pool(scans, segs, board)
    spacing = _ring_spacing(theta, float(np.max(np.diff(np.sort(scans[0].lasers.elevation)))))
    win = max(p.window, p.window_rings * spacing)
    # `board_coordinates` of the pool and the rays within the window, in one compiled pass
    # (the same floats): no products, masks or gathers over the whole pool for the rays kept
    keep, x, z, lam = window_rays(cat[0], cat[1], rotation(theta[3], theta[4], theta[5]),
                                  float(theta[0]), float(theta[1]), float(theta[2]),
                                  board.width / 2 + win, board.height / 2 + win)
    return Rays(*pool_rows(keep, *cat)), (x, z, lam), spacing


#: The last `_candidate_pool`: weak references to its scans and segmentations, its board and
#: its arrays. An estimate fits from several start poses and the pool does not depend on the
#: pose: it is gathered once. Weak, so that the cache never keeps a caller's scans alive.
_last_pool: tuple | None = None


def _candidate_pool(scans: list[Scan], segs: list[Segmentation], board: BoardSpec
                    ) -> list[np.ndarray]:
    """The fired rays of the board's rings (and one more on each side) within its azimuth
    window, from all scans, as the arrays of `Rays`; the same lists of scans and
    segmentations (the same objects, in the same order) reuse the last pool."""
    global _last_pool
    last = _last_pool
    if (last is not None and last[2] == board and len(last[0]) == len(scans)
            and all(r() is s for r, s in zip(last[0], scans, strict=True))
            and all(r() is g for r, g in zip(last[1], segs, strict=True))):
        return last[3]
    parts = []
    offset = 0
    for s, g in zip(scans, segs, strict=True):
        az_b = s.azimuth[g.board]
        c = float(np.angle(np.mean(np.exp(1j * az_b))))
        rel_b = unwrap(az_b, c)
        # wide enough for the whole board even if only part of it returned (a dark patch, an
        # occluder), at any in-plane rotation: the rectangle must not extend where no ray was
        # looked at
        margin = board.diagonal / max(float(np.median(s.distance[g.board])), 0.5)
        lo, hi = rel_b.min() - margin, rel_b.max() + margin
        lasers = s.lasers
        rings = lasers.ring_of_laser[s.laser_id[g.board]]
        # the board's rings and one more on each side, within the window, and their rays: one
        # compiled pass over the scan (`window_pool`, the floats of `Scan.origins`,
        # `Scan.directions`), without masks over every firing
        applied = s.vertical_offsets_applied
        offset_z = (np.array(lasers.vertical_offset, dtype=np.float64)  # writable, as zeros:
                    if applied else np.zeros(lasers.n_lasers))  # one type
        offset_h = (np.array(lasers.horizontal_offset, dtype=np.float64)
                    if applied else np.zeros(lasers.n_lasers))
        idx, *rays_in = window_pool(s.azimuth, s.laser_id, s.distance, lasers.ring_of_laser,
                                    np.cos(lasers.elevation), np.sin(lasers.elevation),
                                    offset_z, offset_h, c, float(lo), float(hi),
                                    int(rings.min()) - 1, int(rings.max()) + 1)
        parts.append((*rays_in, idx + offset, np.full(len(idx), len(parts))))
        offset += len(s)
    cat = [np.concatenate(p) for p in zip(*parts, strict=True)]
    _last_pool = ([weakref.ref(s) for s in scans], [weakref.ref(g) for g in segs], board, cat)
    return cat


def rays_of(scan: Scan, idx: np.ndarray, lid: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
    """``scan.select(idx).origins()`` and ``.directions()`` without the other seven arrays'
    gathers: the same floats (each laser's elevation's cosine and sine taken from its table's
    once: an elementwise function gives the same value wherever its argument sits). ``lid``:
    ``scan.laser_id[idx]``, if the caller has it."""
    lasers = scan.lasers
    if lid is None:
        lid = scan.laser_id[idx]
    az = scan.azimuth[idx]
    ce = np.cos(lasers.elevation)[lid]
    u = np.empty((len(lid), 3))
    u[:, 0] = ce * np.sin(az)
    u[:, 1] = ce * np.cos(az)
    u[:, 2] = np.sin(lasers.elevation)[lid]
    o = lasers.origins(lid, az) if scan.vertical_offsets_applied else np.zeros((len(lid), 3))
    return o, u


def _ring_spacing(theta: np.ndarray, spacing: float) -> float:
    """How far apart on the board two rings ``spacing`` (rad) apart cross its centre, m: the
    range times the spacing, stretched where the board is tilted away from the rays."""
    r = rotation(theta[3], theta[4], theta[5])
    n, d = r[1], -theta[1]
    u = -r.T @ theta[:3]  # the board's centre in {L}
    u /= np.linalg.norm(u)
    up = np.array([0.0, 0.0, 1.0]) - u[2] * u
    up /= max(float(np.linalg.norm(up)), 1e-9)
    p = [(d / float(v @ n)) * v for v in (u + 0.5 * spacing * up, u - 0.5 * spacing * up)]
    return float(np.linalg.norm(p[0] - p[1]))

"""Which rings a set of returns lies on: the board's rings, a consecutive block of them."""

from __future__ import annotations

import numpy as np

from align.search.cluster_kernels import in_ring_block
from twin.core.scan import Scan


def on_board_rings(scan: Scan, idx: np.ndarray) -> np.ndarray:
    """The returns ``idx`` of a board cluster on its `consecutive_ring_block`: the board's own
    rings. The clustering joins rings up to `RING_RADIUS_SPACINGS` apart (a board turned by 60
    deg), which also reaches a stand's face a ring or two below the board, coplanar within
    the plane fit's band: methods that fit a plane to every return (the paper's, ICP) must
    leave it out first or it tilts their plane by tenths of a degree."""

    ring = scan.lasers.ring_of_laser[scan.laser_id[idx]]  # (Scan.ring maps every firing)
    return idx[in_ring_block(ring, np.ones(len(ring), dtype=np.bool_))]


def consecutive_ring_block(rings: np.ndarray) -> list[int]:
    """The consecutive block of rings holding the most of these returns (a ring counts as present
    with a quarter of the busiest ring's returns). The board's rings are consecutive; a parallel
    face in front of it (the stand's base) lights up a ring or two beyond a gap."""
    per_ring = np.bincount(rings) if len(rings) else np.zeros(0, dtype=np.int64)
    present = per_ring >= 0.25 * per_ring.max() if len(rings) else per_ring > 0
    blocks, cur = [], []
    for r in range(len(per_ring)):
        if present[r]:
            cur.append(r)
        elif cur:
            blocks.append(cur)
            cur = []
    if cur:
        blocks.append(cur)
    return max(blocks, key=lambda b: per_ring[b].sum()) if blocks else []

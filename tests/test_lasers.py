"""The laser table a scan carries: its rings, angles and offsets are its own sensor's."""

from __future__ import annotations

import numpy as np
import pytest

from twin.core import vlp16
from twin.core.lasers import LaserTable
from twin.core.scan import Scan, points_from_polar


def test_the_vlp16_table_is_the_manuals():
    t = vlp16.LASERS
    assert t.n_lasers == 16
    np.testing.assert_allclose(t.elevation_deg, vlp16.ELEVATION_DEG, atol=1e-12)
    # ring 0 is the lowest beam (-15 deg, laser 0), ring 15 the highest (+15 deg, laser 15)
    assert t.laser_of_ring[0] == 0 and t.laser_of_ring[-1] == 15
    np.testing.assert_array_equal(t.ring_of_laser[t.laser_of_ring], np.arange(16))
    with pytest.raises(ValueError):
        t.elevation[0] = 0.0  # read-only: a table is shared by every scan of its sensor


def test_a_table_checks_its_lengths():
    with pytest.raises(ValueError, match="vertical_offset has 2 entries, expected 3"):
        LaserTable("x", [0.0, 0.1, 0.2], vertical_offset=[0.0, 0.0])
    with pytest.raises(ValueError, match=r"1\.\.255 lasers"):
        LaserTable("x", [])


def test_a_scan_reads_its_own_table():
    """A 32-laser table (+-10 deg, offsets on odd lasers): rings, elevations, origins and points
    come from it."""
    el = np.deg2rad(np.linspace(-10, 10, 32))[np.r_[0:32:2, 1:32:2]]  # interleaved firing order
    vo = np.where(np.arange(32) % 2, 0.004, -0.004)
    t = LaserTable("test-32", el, vertical_offset=vo)
    lid = np.arange(32, dtype=np.uint8)
    dist = np.full(32, 5.0)
    az = np.full(32, 0.3)
    x, y, z = points_from_polar(dist, az, lid, lasers=t)
    zeros = np.zeros(32)
    scan = Scan(dist, az, lid, zeros.astype(np.uint8), zeros, zeros.astype(np.uint8), x, y, z,
                lasers=t)
    np.testing.assert_allclose(scan.elevation, el)
    assert sorted(scan.ring.tolist()) == list(range(32))
    assert scan.ring[0] == 0 and scan.ring[16] == 1  # laser 16 fires the second-lowest beam
    np.testing.assert_allclose(scan.origins()[:, 2], vo)
    np.testing.assert_allclose(scan.xyz, scan.origins() + 5.0 * scan.directions(), atol=1e-12)
    assert scan.select(scan.valid).lasers is t  # selections keep the table

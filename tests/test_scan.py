"""The Scan container and the polar-to-Cartesian convention of DESIGN.md."""

import numpy as np
import pytest

from twin.core import vlp16
from twin.core.scan import Scan, points_from_polar


def test_rings_are_elevation_order():
    el = vlp16.ELEVATION_DEG[vlp16.LASER_OF_RING]
    assert np.all(np.diff(el) > 0)
    assert vlp16.RING_OF_LASER[0] == 0 and vlp16.RING_OF_LASER[15] == 15
    assert vlp16.RING_OF_LASER[1] == 8  # +1 deg is the ninth beam from the bottom


@pytest.mark.parametrize(
    ("az_deg", "expected"),
    [(0.0, (0.0, 1.0, 0.0)), (90.0, (1.0, 0.0, 0.0)), (180.0, (0.0, -1.0, 0.0))],
)
def test_azimuth_is_clockwise_from_forward(az_deg, expected):
    # laser 1 fires at +1 deg: divide its elevation out to check the horizontal direction
    x, y, z = points_from_polar(np.array([10.0]), np.deg2rad([az_deg]), np.array([1]),
                                vertical_offsets=False)
    c = np.cos(np.deg2rad(1.0))
    np.testing.assert_allclose([x[0] / (10 * c), y[0] / (10 * c)], expected[:2], atol=1e-12)
    np.testing.assert_allclose(z[0], 10 * np.sin(np.deg2rad(1.0)))


def test_vertical_offset_applied_only_to_returns():
    d = np.array([5.0, 0.0])
    _, _, z = points_from_polar(d, np.zeros(2), np.array([0, 0]))
    assert z[0] == pytest.approx(5 * np.sin(np.deg2rad(-15)) + 0.0112)
    assert z[1] == 0.0


def test_select_concatenate_and_length_check():
    n = 5
    d = np.linspace(0, 4, n)
    az = np.zeros(n)
    lid = np.arange(n, dtype=np.uint8)
    x, y, z = points_from_polar(d, az, lid)
    s = Scan(d, az, lid, np.zeros(n, np.uint8), np.zeros(n), np.ones(n, np.uint8), x, y, z)
    assert len(s.hits()) == 4
    both = Scan.concatenate([s, s.hits()])
    assert len(both) == 9
    with pytest.raises(ValueError, match="laser_id"):
        Scan(d, az, lid[:2], np.zeros(n, np.uint8), np.zeros(n), np.ones(n, np.uint8), x, y, z)

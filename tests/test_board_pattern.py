"""The twin's patterned board: a chessboard of two reflectivities on the board's face.

Each return that lands on the board is placed on the pattern through the scan's true pose; its
square's colour must be the one `BoardPattern` says, as the intensities show (dark squares dim,
or no return at all when their reflectance is 0).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from twin.sim.bench import BenchSim
from twin.sim.emulation import EmulationConfig
from twin.sim.params import BenchParams, BoardPattern

#: The twin's board (0.90 x 0.54 m) with a 9 x 4 chessboard of 90 mm squares (the rings cross
#: the board 2 deg = 91 mm apart at +-47 and +-140 mm: mid-square, for this test).
PATTERN = BoardPattern(rows=4, cols=9, square=0.09, dark_reflectivity=0.03,
                       light_reflectivity=0.8)
SHARP = EmulationConfig(laser_offset_sigma=0.0, divergence=False)


def _on_board(scan, pattern: BoardPattern):
    """Returns on the board's face, their square's darkness, and how far inside the square."""
    p = scan.meta["truth_pose"].transform(scan.xyz)
    w, h = pattern.size
    col = np.floor((p[:, 0] - pattern.offset[0] + w / 2) / pattern.square)
    row = np.floor((pattern.offset[1] + h / 2 - p[:, 2]) / pattern.square)
    u = (p[:, 0] - pattern.offset[0] + w / 2) / pattern.square - col
    v = (pattern.offset[1] + h / 2 - p[:, 2]) / pattern.square - row
    inner = np.minimum.reduce([u, 1 - u, v, 1 - v]) * pattern.square  # m to the square's edge
    on = (scan.valid & (np.abs(p[:, 1]) < 0.06) & (col >= 0) & (col < pattern.cols)
          & (row >= 0) & (row < pattern.rows))
    return on, (row + col) % 2 == 0, inner


def test_chessboard_squares_return_their_reflectivity():
    sim = BenchSim(BenchParams(board_pattern=PATTERN), seed=1, noise=SHARP)
    scan = sim.scan()
    on, dark, inner = _on_board(scan, PATTERN)
    safe = on & (inner > 0.01)  # 10 mm inside a square: no doubt which square a ray hit
    i_dark, i_light = scan.intensity[safe & dark], scan.intensity[safe & ~dark]
    assert len(i_dark) > 50 and len(i_light) > 50
    # calibrated reflectivity: about 100 x reflectance x cos(incidence)
    assert i_dark.max() < 15 and i_light.min() > 40, (i_dark.max(), i_light.min())
    # the print stands 0.1 mm proud of the plate: the squares' face is the board's, nearly
    geom = sim.physics.model.geom(PATTERN.squares()[0][0])
    np.testing.assert_allclose(geom.size, [0.045, 5e-5, 0.045])


def test_black_squares_of_zero_reflectance_drop_out():
    pattern = replace(PATTERN, dark_reflectivity=0.0)
    scan = BenchSim(BenchParams(board_pattern=pattern), seed=2, noise=SHARP).scan()
    on, dark, inner = _on_board(scan, pattern)
    assert np.sum(on & ~dark & (inner > 0.01)) > 100
    assert np.sum(on & dark & (inner > 0.01)) == 0


def test_pattern_must_fit_on_the_board():
    with pytest.raises(ValueError, match="does not fit"):
        BenchParams(board_pattern=BoardPattern(rows=7, cols=5, square=0.095))
    with pytest.raises(ValueError, match="reflectance"):
        BoardPattern(rows=2, cols=2, square=0.1, dark_reflectivity=1.5)
    with pytest.raises(ValueError, match="rows"):
        BoardPattern(rows=0, cols=2, square=0.1)

"""The target board: a flat rectangle whose front face is the plane Y_O = 0 of the board frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class BoardSpec:
    """Size of the rectangular target board, m (the paper's bench: 0.90 m x 0.54 m).

    The board frame {O} of DESIGN.md has its origin at the centre of the front face, X_O to the
    right, Z_O up; the corners are (+-width/2, 0, +-height/2).
    """

    width: float = 0.90
    height: float = 0.54
    #: Plate thickness, m. A ray seen obliquely can pass the front face's edge and still hit the
    #: plate's side face: the board then looks wider on the side facing the LiDAR by up to
    #: thickness x tan(incidence) (about 1 mm at 3 mm and 20 deg, ten times a fused bracket's
    #: width). 3 mm: the twin's plate (models/target_board.xml); measure the real one.
    thickness: float = 0.003
    #: 1-sigma of the width and height given, m: a board measured with a tape. What the size the
    #: rays see is compared with (`align.fit.size.size_mismatch`).
    size_std: float = 0.001

    def __post_init__(self) -> None:
        if not (self.width > 0 and self.height > 0 and self.thickness >= 0
                and self.size_std >= 0):
            raise ValueError(f"board size must be positive, got {self.width} x {self.height} m "
                             f"x {self.thickness} m")

    @property
    def half(self) -> np.ndarray:
        """(width/2, height/2), m."""
        return np.array([self.width / 2, self.height / 2])

    @property
    def diagonal(self) -> float:
        """Length of the diagonal, m."""
        return float(np.hypot(self.width, self.height))

    def corners(self) -> np.ndarray:
        """The four corners in {O}, (4, 3), m, in the paper's order (Eq. 3).

        Top-left, top-right, bottom-left, bottom-right: (-W/2, 0, H/2), (W/2, 0, H/2),
        (-W/2, 0, -H/2), (W/2, 0, -H/2).
        """
        w, h = self.width / 2, self.height / 2
        return np.array([[-w, 0.0, h], [w, 0.0, h], [-w, 0.0, -h], [w, 0.0, -h]])

    @classmethod
    def from_mm(cls, text: str) -> BoardSpec:
        """Parse ``"900x540"`` (width x height in mm), the CLI's form."""
        try:
            w, h = (float(v) for v in text.lower().split("x"))
        except ValueError as exc:
            raise ValueError(f"board size {text!r}: expected WIDTHxHEIGHT in mm, e.g. 900x540") \
                from exc
        return cls(width=w * 1e-3, height=h * 1e-3)

"""The joint least-squares model of the pose: whitened range residuals of hits inside the
rectangle and bracket residuals at its edges, with their assignment to edges."""

from __future__ import annotations

import numpy as np

from align.board import BoardSpec
from align.fit.bracket_kernels import (
    classify_edges,
    profile_best,
    profile_cost,
    used_edges,
)
from align.fit.brackets import hit_miss_brackets, vertical_brackets
from align.fit.label_kernels import range_rays, ray_products, shifted_coords
from align.fit.lsq_kernels import fit_residuals, jacobian_into
from align.fit.rays import HIT, MISS, Rays
from align.geometry import board_coordinates, lidar_up, rotation
from align.params import RaysParams


class Model:
    """Whitened residuals of the joint fit for a pose theta."""

    def __init__(self, rays: Rays, lab: np.ndarray, bh: np.ndarray, bm: np.ndarray,
                 board: BoardSpec, sigma_r: float, blur: float, p: RaysParams) -> None:
        self.rays, self.lab, self.board, self.p = rays, lab, board, p
        self.bh, self.bm = bh, bm
        self.sigma_r, self.blur = sigma_r, blur
        # a ring's height on the board is known less well than a position along it: the beam
        # is 1.5 mrad tall (4 mm at 2.6 m) and the laser's elevation is only nominal
        self.blur_z = max(blur, self.p.edge_blur_z)
        # the blur across the side edges and across the top and bottom edges (`set_blur`)
        self.blur_edges = (blur, self.blur_z)
        self.use_range = np.zeros(len(lab), dtype=bool)
        self._range = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
        self._bh = (rays.origin[bh], rays.direction[bh])
        self._bm = (rays.origin[bm], rays.direction[bm])
        self.edge_kind = np.zeros(len(bh), dtype=np.int8)  # 0 skip, 1 vertical edge, 2 horizontal
        self.edge_sign = np.zeros(len(bh))
        self.edge_sd = np.ones(len(bh))
        self.excluded = np.zeros(len(bh), dtype=bool)  # left out of every fit (gross errors)
        #: The common range offset the ranges carry (m), and its prior (mean, 1-sigma) when it
        #: is fitted with the pose (`gauss_newton`); None: held at ``offset``.
        self.offset = 0.0
        self.offset_prior: tuple[float, float] | None = None
        #: The last pose's board coordinates of all rays (`coords`): its bytes and (X, Z, lam).
        self._coords: tuple[bytes, tuple[np.ndarray, ...]] | None = None
        #: The rays' products with the last rotation's rows (`_shifted_coords`): the bytes of
        #: (t_y, roll, tilt, yaw) and (o.r0, lam u.r0, o.r2, lam u.r2, lam).
        self._products: tuple[bytes, tuple[np.ndarray, ...]] | None = None
        # the labels stay as built: their hits and misses, for every profile
        self._hits, self._misses = np.flatnonzero(lab == HIT), np.flatnonzero(lab == MISS)
        self._cache_edges()

    def coords(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`board_coordinates` of all the model's rays at ``theta``; the last pose's are kept:
        a fit classifies, assigns and profiles at the same pose several times. Read only."""
        theta = np.asarray(theta, dtype=np.float64)
        key = theta.tobytes()
        if self._coords is None or self._coords[0] != key:
            self._coords = (key, self._shifted_coords(theta))
        return self._coords[1]

    def _shifted_coords(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`board_coordinates` at ``theta``, its expressions term by term (so the same bits),
        reusing the products with the rotation rows where only the in-plane position moved
        since the last pose (a profile's shift, every other new pose of a fit): X = (o.r0 +
        t_x) + lam u.r0 and Z alike, lam depending on t_y and the rotation alone."""
        rkey = theta[[1, 3, 4, 5]].tobytes()
        if self._products is None or self._products[0] != rkey:
            # `ray_products`: the floats of `board_coordinates`' matrix-vector products and
            # elementwise steps, so a shifted pose's coordinates equal a fresh computation's
            self._products = (rkey, ray_products(self.rays.origin, self.rays.direction,
                                                 rotation(theta[3], theta[4], theta[5]),
                                                 float(theta[1])))
        ox, ux, oz, uz, lam = self._products[1]
        return (*shifted_coords(ox, ux, oz, uz, float(theta[0]), float(theta[2])), lam)

    def _cache_edges(self) -> None:
        """The used brackets' rays, signs and sigmas, contiguous (the fit only reads these)."""
        oh, uh, om, um, self._usign, self._usd, self._uvert = used_edges(
            self.edge_kind, *self._bh, *self._bm, self.edge_sign, self.edge_sd)  # compiled
        self._ubh, self._ubm = (oh, uh), (om, um)

    def assign(self, theta: np.ndarray) -> None:
        """Which hits feed the range residuals: those safely inside the rectangle."""
        w2, h2 = self.board.width / 2, self.board.height / 2
        x, z, lam = self.coords(theta)
        r = self.rays
        # the fit only ever looks at these rays: kept contiguous (`range_rays`)
        self.use_range, *rng = range_rays(x, z, lam, r.origin, r.direction, r.distance,
                                          self.lab == 1, float(self.offset),
                                          w2 - self.p.edge_margin,
                                          h2 - self.p.edge_margin, 4 * self.sigma_r)
        self._range = tuple(rng)

    def classify(self, theta: np.ndarray, guard: float, crossings: bool = True) -> None:
        """Fix which edge each bracket measures, for pose ``theta``; drop the ambiguous ones.

        The line through a bracket's hit and miss meets the side edge X = +-W/2 (on the side it
        heads to) at some height z_at: well within the board's height (by ``guard``, m: the
        pose's own uncertainty there) the bracket measures that side edge; well beyond it,
        the top or bottom edge; in between (a bracket at a corner) it could be either and is
        left out. Assignments stay fixed during a fit: switching them inside Gauss-Newton
        makes the cost jump and traps the fit in wrong basins.
        """
        x, z, _ = self.coords(theta)
        self.set_blur(theta)
        # `_edges` for the brackets, compiled; without crossings, rings that cross an edge at
        # a grazing angle (a level board's top or bottom edge) are left out: such a bracket is
        # sharp across its edge, and wrong if matched to the wrong edge
        self.edge_kind, self.edge_sign, self.edge_sd = classify_edges(
            x, z, self.bh, self.bm, self.board.width / 2, self.board.height / 2, guard,
            *self.blur_edges, crossings, self.p.grazing, self.excluded)
        self._cache_edges()

    def set_blur(self, theta: np.ndarray) -> None:
        """The blur across each pair of edges at pose ``theta``: along the rings ``blur``,
        across them (the LiDAR's up direction) ``blur_z``, mixed by the edge's direction."""
        vx, vz = lidar_up(theta)
        self.blur_edges = (float(np.hypot(self.blur * vz, self.blur_z * vx)),
                           float(np.hypot(self.blur * vx, self.blur_z * vz)))

    def _width(self, theta: np.ndarray) -> np.ndarray:
        """Each bracket's extent across its edge (m) at pose theta."""
        x, z, _ = self.coords(theta)
        return np.where(self.edge_kind == 1, x[self.bm] - x[self.bh], z[self.bm] - z[self.bh])

    def profile(self, theta: np.ndarray, ds: np.ndarray, tol: float | None = None) -> np.ndarray:
        """A cost for the pose shifted by each of ``ds`` (m) along the LiDAR's up direction in
        the plane (`lidar_up`: z for a level board): label violations first.

        The shift moves every board coordinate by the same amount and leaves the ranges alone,
        so the profile is cheap. The cost counts hits outside the rectangle and misses inside it
        (more than ``tol`` from its edge), then adds the brackets' squared residuals with their
        edges reassigned for each shift: one compiled pass (`profile_cost`), without a
        (brackets x shifts) temporary.
        """
        x, z, _ = self.coords(theta)
        vx, vz = lidar_up(theta)
        return profile_cost(x, z, self._hits, self._misses,
                            self.bh, self.bm, np.asarray(ds, dtype=np.float64), vx, vz,
                            self.board.width / 2, self.board.height / 2,
                            self.p.profile_tol if tol is None else tol, *self.blur_edges)

    def shift(self, theta: np.ndarray, ds: np.ndarray) -> np.ndarray:
        """``theta`` moved to the cheapest shift of `profile` over ``ds`` (its first minimum,
        `profile_best`: the brackets costed only where they can decide)."""
        x, z, _ = self.coords(theta)
        vx, vz = lidar_up(theta)
        s = float(ds[profile_best(x, z, self._hits, self._misses, self.bh, self.bm,
                                  np.asarray(ds, dtype=np.float64), vx, vz,
                                  self.board.width / 2, self.board.height / 2, self.p.profile_tol,
                                  *self.blur_edges)])
        out = theta.copy()
        out[0] += s * vx
        out[2] += s * vz
        return out

    def _fit_arrays(self) -> tuple:
        """The arrays and constants `fit_residuals` reads, in its order after
        (theta, rot)."""
        return (*self._range, float(self.offset), float(self.sigma_r), *self._ubh, *self._ubm,
                self._usign, self._usd, self._uvert, self.board.width / 2,
                self.board.height / 2, float(self.board.thickness))

    def residuals(self, theta: np.ndarray) -> np.ndarray:
        """Whitened residuals: ranges of the interior hits, then the used brackets.

        A bracket's residual is its edge's position minus the middle of its hit's and miss's
        points on the board, over its sigma; the plate's side face puts the edge further out
        for a ray heading inwards that passes the front edge by less than thickness x (its
        lateral over forward direction): it still hits the board. One compiled pass over the
        rays (`fit_residuals`)."""

        theta = np.asarray(theta, dtype=np.float64)
        rot = rotation(theta[3], theta[4], theta[5])
        return fit_residuals(theta, rot, *self._fit_arrays())

    def jacobian(self, theta: np.ndarray, f0: np.ndarray) -> np.ndarray:
        """d residuals / d theta: translations analytically, rotations by forward differences.

        X = o.r0 + t_x + lam u.r0, Z = o.r2 + t_z + lam u.r2, lam = -(o.r1 + t_y) / u.r1 (r_k
        the rows of R): t_x and t_z move X and Z one for one; t_y moves lam by -1 / u.r1.
        The fit's own (`jacobian_into`, which `lm_fit` calls in its loop).
        """

        f0 = np.asarray(f0, dtype=np.float64)
        j = np.zeros((len(f0), 6))
        jacobian_into(np.asarray(theta, dtype=np.float64), f0, *self._fit_arrays(),
                       JACOBIAN_STEP, j, np.empty(len(f0)))
        return j


#: The forward difference of the rotations in `Model.jacobian`, rad.
JACOBIAN_STEP = 1e-7


def build_model(rays: Rays, lab: np.ndarray, theta: np.ndarray, board: BoardSpec,
                 sigma_r: float, blur: float, like: Model | None = None,
                 offset: tuple[float, tuple[float, float] | None] = (0.0, None),
                 coords: tuple[np.ndarray, ...] | None = None, *, p: RaysParams) -> Model:
    """Brackets along the rings and between rings at the board's centre column, as a model.
    Its range offset and the offset's prior: ``like``'s (a model rebuilt), else ``offset``.
    ``coords``: the rays' board coordinates at ``theta`` if the caller has them."""
    if coords is None:
        coords = board_coordinates(theta, rays.origin, rays.direction)
    x, z, _ = coords
    vx, vz = lidar_up(theta)
    bh, bm = hit_miss_brackets(rays, lab, p=p)
    vh, vm = vertical_brackets(rays, lab, np.abs(vz * x - vx * z))
    model = Model(rays, lab, np.concatenate((bh, vh)), np.concatenate((bm, vm)), board,
                   sigma_r, blur, p)
    model.offset, model.offset_prior = (like.offset, like.offset_prior) if like else offset
    model._coords = (np.asarray(theta, dtype=np.float64).tobytes(), coords)
    return model

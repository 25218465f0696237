"""The `rays` method's tuning: one frozen object, passed in (`align.estimate(..., params=)`).

Each field is a constant of the method with the reason for its value; the defaults are the values
every figure in docs/align.md was measured with. `align.Hints` is what a user says about the
scene (range noise, beam, priors); this is how the method works, which a user rarely changes.
Lengths in m, angles in rad.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RaysParams:
    """The tuning of method="rays" (see each field)."""

    # The plane (`align.rays.plane_steps`, `align.rays.pipeline`)

    #: Returns farther than this many sigma from the plane are not the board's face (the stand, a
    #: mixed return at an edge); the variance of a unit Gaussian cut there (1 - 2 c phi(c) /
    #: (2 Phi(c) - 1)) corrects the noise estimated from the rest.
    trim: float = 2.5
    #: The prior 1-sigma of a common range offset taken as known (only per-laser offsets
    #: uncertain), m: a number, not zero, so that the joint fit's normal matrix stays regular.
    offset_known: float = 1e-06
    #: The least range noise assumed, m: a noise-free simulation (or one return per ring) still gets
    #: a plane of finite uncertainty.
    range_sigma_floor: float = 0.001
    #: A return is inside the fitted rectangle (`inside_returns`) by more than this, m: half the
    #: VLP-16's beam footprint at 2.5 m and more (a mixed return's range is part background's),
    #: and about the fit's uncertainty across a side edge. Not the fit's uncertainty across the
    #: top and bottom edges (1-3 cm for one scan): the rings lie 9 cm apart there, and a margin
    #: that wide leaves out a whole ring near an edge, and with it the plane's tilt (measured: the
    #: roll, which the plane carries, 5 % further from its bound on random scenes).
    inside_margin: float = 0.005
    #: The plane of the returns inside the fitted rectangle replaces the cluster's when the two
    #: differ by more than this (chi-square of 3 degrees of freedom in the rectangle's plane's
    #: covariance: 1 in 20 by chance between independent samples; the nested ones of a cluster
    #: that held only the board differ far less: on 300 scans of the paper's bench the median
    #: 0.15, the largest 5.8; on random scenes 6 % of the scans are above).
    plane_moved_chi2: float = 7.8
    #: The returns the first ML plane is fitted to lie within this of the start plane, m (3.5
    #: sigma of the VLP-16's 14 mm), or within `start_band_sigmas` of their own spread where that
    #: is wider: a band of 1.8 sigma (28 mm of noise) kept the noise that leans towards the start
    #: plane, and tilt's chi2 was 2.6 fused.
    start_band: float = 0.05
    start_band_sigmas: float = 3.0
    #: The search kept a cluster's returns within `align.search.board.FLAT_BAND` of its plane;
    #: where that band is within this many sigmas of the ranges' spread (the cluster's own,
    #: robust) the cut leans the plane fitted to what it kept, and the plane is fitted to every
    #: return of the cluster's rings within the azimuths each spans in it instead (21 mm of
    #: noise, a 1.9 sigma cut: tilt 1.23 x its bound, chi2 1.4-3.8; at 14 mm, 2.9 sigma, the
    #: returns it gives back changed the ratios by 0.03 at most, and they take in a box a few cm
    #: behind the board's edge: so only below this).
    pool_cut_sigmas: float = 2.5

    # The rays near the board (`align.fit.rays`)

    #: Labels farther than this inside (misses) or outside (hits) the start pose's rectangle are not
    #: edge information but dropouts or strays, m.
    outlier_margin: float = 0.03
    #: Rays considered: within this of the rectangle's edges (board coordinates), m: one ring
    #: spacing (2 deg at 2.6 m = 91 mm) plus the lean of a rolled ring, not much more (the board's
    #: stand, 5 cm in front of the plane, sits lower) ...
    window: float = 0.13
    #: ... or 1.2 ring spacings at the board's distance where that is more (a far board: the ring
    #: beyond its edge must be looked at).
    window_rings: float = 1.2

    # Labels (`align.fit.labels`)

    #: A return within this distance of the plane (along the ray) is a hit on the board, m. The
    #: nearest thing behind the paper's board (its stand) is 0.15 m behind it; the noise is 14 mm.
    label_tolerance: float = 0.07
    #: A hit is a return within this many range sigmas of the plane (and `label_tolerance`); one
    #: farther in front is something before the board (unknown), one farther behind but within
    #: `label_tolerance` may be a thing close behind it (unknown too): a stand or its clamp near
    #: the board's edge, whose returns would otherwise count as hits beside the board. 3.5 sigma
    #: leaves out 5 in 10,000 of the board's own returns, which as unknowns cost nothing.
    front_sigmas: float = 3.5
    #: The board shows dropouts when more of its rays than this (and at least `min_dropouts`) return
    #: nothing although the same laser hits the board on both sides of them.
    dropout_fraction: float = 0.01
    min_dropouts: int = 3
    #: A laser's outermost hits are something just behind the board beside its edge (a holder, a
    #: box standing behind it) when their mean range residual is this many standard errors and at
    #: least `behind_min` behind the plane (`behind_ends`). 5 sigma: a board's own ends pass
    #: (about 1 in 1000 scans trims an end it should not, which costs a bracket, not a bias).
    behind_sigmas: float = 5.0
    behind_min: float = 0.01
    #: At most this many hits from each end are tested, and at least this many at once.
    behind_reach: int = 40
    behind_run: int = 3
    #: A laser's run of hits that starts and ends on the same straight edge rides along it within
    #: the ring's sag over the run (a ring is a cone's trace on the plane, nearly straight: a
    #: 0.1 m run of the VLP-16's lowest ring at 2.5 m bends by 0.06 mm). A ring's height against an
    #: edge is as good as random over its spacing on the board (90 mm there), so a run that needs
    #: the edge within less than this of the ring (m) is the board by a chance of about 1 in 1000,
    #: and a holder or bracket just behind the edge (a few cm of hits on a ring that passes the
    #: board) by far the likelier (`grazing_runs`).
    graze_sag: float = 0.0001
    #: A short run this near a corner (beyond its own length, m) may end on the two edges that meet
    #: there: a ring crossing the corner, not grazing.
    corner_reach: float = 0.05
    #: A hit at a laser's end brighter than this many times the board's brightest inner hits (their
    #: 99th percentile) is not the board's: a holder of another material beside the edge, flush
    #: with the plane within the range noise (`bright_ends`). A board's own edge returns no
    #: brighter than its face: a beam partly on it returns less. (Not so for dimmer: a partial
    #: return, the plate's side face met at a grazing angle, are the board's and dim.)
    bright_ratio: float = 1.15
    #: ... judged only against this many inner hits or more.
    bright_reference: int = 20

    # Brackets (`align.fit.brackets`)

    #: Consecutive transitions closer than this (in azimuth, rad) form one mixed zone.
    zone_azimuth: float = float(np.deg2rad(0.5))
    #: Neighbours farther apart than this in azimuth bracket nothing (a dropped firing), rad;
    #: at least `GAP_STEPS` of the sensor's own firing step (`for_firing_step`).
    max_gap: float = float(np.deg2rad(0.7))

    # The least-squares model (`align.fit.model`)

    #: Range residuals only from hits at least this far inside the rectangle, m (beam footprint
    #: 3 mrad x 2.6 m = 8 mm, half of it plus the azimuth step).
    edge_margin: float = 0.015
    #: 1-sigma of a top/bottom edge crossing across the ring (the ring's height), m.
    edge_blur_z: float = 0.002
    #: A bracket whose extent across its edge is below this fraction of its extent along it comes
    #: from a ring crossing the edge at a grazing angle (under 14 deg).
    grazing: float = 0.25
    #: How far outside the rectangle a hit (inside it a miss) violates its label in the profile
    #: across the rings (`Model.profile`), m.
    profile_tol: float = 0.003

    # The least-squares fit (`align.fit.lsq`)

    #: A hit farther than this outside the rectangle (after the z profile) is not the board, m.
    stray: float = 0.04
    #: A bracket whose whitened residual exceeds this is a gross error (`_gross_brackets`).
    gross: float = 8.0
    #: The profile across the rings reaches at least this many ring spacings (on the board) either
    #: side, and a hit is a stray at least this many of them outside the start rectangle.
    profile_spacings: float = 0.6
    stray_spacings: float = 0.4

    # The side edges (`align.fit.sides`)

    #: A laser's hits may span the board's width by this much more (m) before one end is taken to
    #: overhang: the plane's distance error scales the span (5 mm: 0.6 % of the 0.9 m board).
    span_slack: float = 0.005
    #: A laser's end is at a side edge when it lies within this of it (m) at the fit's pose: what
    #: a few degrees of roll move it over the board's height.
    edge_reach: float = 0.05
    #: A laser's end lies beyond the side lines by more than half the step between its hits and
    #: this (m: the lines' error through a handful of ends, the plane's) when something beside the
    #: edge lengthens its run. Leaving out a board's own last hit costs little; keeping a holder's
    #: hit outside the edge empties the hit/miss posterior.
    overhang_slack: float = 0.003
    #: The side lines need this many lasers' ends at each side, and this many in all (three
    #: unknowns: an offset per side and the common slope).
    side_ends: int = 2
    #: The side lines need this many lasers' ends at each side, and this many in all (three
    #: unknowns: an offset per side and the common slope).
    line_ends: int = 5

    # Starts (`align.fit.starts`, `align.rays.pipeline`)

    #: A roll prior narrows the search to this many standard deviations either side.
    prior_reach: float = 4.0
    #: A best fit contradicting more labels than this (by 1 cm, `_contradicted`) is tried again from
    #: the mount's nominal roll.
    retry_violations: int = 10
    #: More than this fraction of the returns left out by the best start's rectangle: something
    #: else shares the board's plane (`held_by`).
    spill: float = 0.05

    # The hit/miss posterior's rays and strays (`align.posterior.rays`, `align.rays.pipeline`)

    #: The chance that a ray passing just beyond the board's edge meets something within the hit
    #: band (`front_sigmas`) of its plane: a holder, a clamp, a box close behind the board. Rare:
    #: 1 in 200. Larger chances (0.01-0.05, measured on random scenes, docs/align.md) also soften
    #: the board's own edge hits at 2-3 sigma, and the posterior loses more there than it gains
    #: from the holders' returns.
    clutter_chance: float = 0.005
    #: A hit is a partial return (the beam only partly on the board) below this fraction of the
    #: board's own intensity: a beam whose centre lies outside the edge has less than half of its
    #: energy on the board (a symmetric spot), one whose centre is on it at least half.
    partial_intensity: float = 0.5
    #: Labels the pose of the least-squares fit violates by more than this (m) may be strays (the
    #: stand beside a rolled board: 2-3 cm; a real scan's edge hits, 3-10 mm outside with a 3 cm
    #: range offset, are not) ...
    stray_violation: float = 0.01
    #: ... and at most this many of them (or this fraction of the labels) are dropped, in at most
    #: this many rounds (each refits without the last round's).
    max_strays: int = 16
    max_stray_fraction: float = 0.01
    stray_rounds: int = 3

    # The result (`align.rays.pipeline`)

    #: At least this many hit/miss brackets (3 in-plane unknowns: roll, x, z, and one to spare).
    min_brackets: int = 4
    #: The size the rays see (`align.fit.size`) refuses the size given beyond this squared
    #: Mahalanobis distance (2 degrees of freedom: 1 in 10,000 by chance): the size is then
    #: freed and the pose moved to where the rays put it, its covariance widened. Below it the
    #: size is taken as given and nothing changes: the fit leans only where the size is wrong.
    size_refused_d2: float = 18.4
    #: The most oblique a board can be seen and measured, rad: the angle between the line of
    #: sight to its centre and its normal. Beyond it (75 deg: a quarter of its width seen) the
    #: edges along the line of sight are not measured and the fit is not vouched for
    #: (partial_board); a cabinet's side seen edge-on passed as a board 86-92 deg off
    #: (bench_align.py --distractors). Boards are inspected within 60 deg.
    max_incidence: float = math.radians(75.0)
    #: A board whose seen size the rays hold off the size given (`size_refused_d2`) by more
    #: than this fraction in width or height is not vouched for (partial_board, the sizes
    #: said): another object, or a size given wrong. A board reads within a few % of its
    #: drawing (the five real scans: 1-2.5 %, their ranges 3 cm long); a cabinet's face passed
    #: as a board 7-10 % off (bench_align.py --distractors).
    size_refused_ratio: float = 0.05

    @property
    def trimmed_variance(self) -> float:
        """The variance of a unit Gaussian cut at `trim` sigma (1 - 2 c phi(c) / (2 Phi(c) -
        1)): corrects the noise estimated from the rest."""
        c = self.trim
        return 1.0 - 2.0 * c * math.exp(-c**2 / 2) / math.sqrt(2 * math.pi) / math.erf(
            c / math.sqrt(2))

    def for_firing_step(self, step: float) -> RaysParams:
        """These parameters for a sensor firing each laser every ``step`` rad: `max_gap` at
        least `GAP_STEPS` steps, so that a sparser sensor's neighbours still bracket an edge (a
        PandarQT128's middle lasers fire every 0.8 deg, past the 0.7 deg set for the VLP-16's
        0.2; every model measured before, 0.18 to 0.4 deg, keeps 0.7; an Ouster of 512
        columns, 0.7 deg, now gets 1.05)."""
        gap = min(GAP_STEPS * step, MAX_GAP)
        if gap <= self.max_gap:
            return self
        return dataclasses.replace(self, max_gap=gap)


#: Neighbours along a laser this many firing steps apart still bracket: one firing dropped
#: (two steps) is a gap, and a step read a little long by the azimuth's rounding is not.
GAP_STEPS = 1.5
#: ... but never more than this, rad (the board search joins nothing farther apart either:
#: `align.search.clusters.MAX_AZIMUTH_GAP`, 1 deg), whatever a scan of a few firings says.
MAX_GAP = math.radians(1.5)

#: The values every figure was measured with.
DEFAULT_PARAMS = RaysParams()


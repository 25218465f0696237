"""The board's choice among the search's candidates: each fitted as the board, judged on the same
terms, the best chosen by a stated likelihood ratio (`decide`).

The board search (`align.search.board`) ranks candidates by a cheap likeness (count,
reflectivity, how a rectangle of the board's size holds them). That ranking picked a
background surface 2.9 m beside the board on a real scan, and the fit then passed: the fit of
a wrong object can pass every check of its own. What tells the board apart is how well the
known rectangle explains each candidate's rays, side by side.

The statistic. Each candidate c that passed gets a log weight w_c; the likelihood ratio of "a
is the board" against "b is" is exp(w_a - w_b), with

    w = g(z) + s + log prior,   g(z) = -max(z, 0)^2 / 2,   z = (D - k) / sqrt(2 k).

- g: the fit's chi-square D over k degrees of freedom (range residuals and the hit/miss labels
  of every ray near the rectangle's edges) is about chi2(k) when c is the board; what the
  residuals of an object that is not the board look like is not modelled (its density taken
  flat). One-sided: a fit better than its noise model (z < 0: the labels' blur set wider than
  this scan needs) is no evidence against a candidate.
- s: the board's size as the rays see it (`align.fit.size`) against the size given, the log
  of the Savage-Dickey ratio of "this object is the known size" to "a flat rectangle of any
  size up to `SIZE_RANGE`": the seen size's density at the given one over the uniform
  prior's. A board whose rays pin its size at the given one earns about +12 (2 mm sigmas); an
  object seen too obliquely or too partly to say its size earns little; one of another size
  loses.
- the prior: what the user says of the board's distance (`Hints.expected_distance`, a
  Gaussian of `DISTANCE_SIGMA`, refused beyond `DISTANCE_REFUSED_SIGMAS`) and the station's
  region (`Hints.board_region`: a Gaussian of a third of its radius about its centre; a
  candidate beyond the radius is refused outright).

The best candidate is chosen when its ratio over every other that passed is at least
`DECISIVE_LR`; otherwise the choice is ambiguous and no pose is reported. Two identical
panels side by side are ambiguous by construction (only a prior can tell them apart), as they
should be: a confident choice between them would be a coin toss. So is a board hidden in part
behind a panel of its own size (`hidden_board`): the panel passes, the board fails its own
fit, and the rays tell that story no better than "a board in front of a panel"; such a failed
candidate is the chosen one's rival, weighed on the priors alone.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from align.geometry import board_centre
from align.result import Hints, PoseEstimate, Status

#: The likelihood ratio the chosen candidate must hold over every other that passed, for the
#: choice to stand (1000: log 6.9, one-sided z 3.7 for a candidate whose fit is the noise's).
DECISIVE_LR = 1000.0
#: The prior on the board's position is a Gaussian whose 1-sigma is this fraction of the
#: station's region radius (the radius taken as 3 sigma), cut off at the radius.
REGION_SIGMAS = 3.0
#: 1-sigma of the distance a user expects the board at (`Hints.expected_distance`), m: a
#: distance stated by eye or from a floor plan, to about a foot. (The search looks much wider:
#: a board's diagonal and 0.5 m either side.)
DISTANCE_SIGMA = 0.3
#: The sizes a flat thing in a workshop may have, m: a uniform prior on each of its width and
#: height (a monitor to a door), what a candidate's seen size is weighed against.
SIZE_RANGE = 2.0
#: Beyond this many `DISTANCE_SIGMA` from the distance the user states, a candidate is not the
#: board (refused, as one beyond the station's region): a board-sized panel 1 m nearer than
#: the board and hiding it passed every check of its own (bench_align.py --distractors).
DISTANCE_REFUSED_SIGMAS = 3.0
#: A candidate that failed only because rays are blocked in front of it (more than this share
#: of its hits), its rectangle holding its hits (at most this share outside) and its fit
#: otherwise sound, is the board partly hidden as much as a candidate that passed is the
#: board (`hidden_board`): the fit's own partial_board limits.
HIDDEN_SHARE = 0.03
#: The edges a partly hidden candidate must show (a miss beyond each) to be taken for the
#: board: a board hidden on one side shows the other three; a patch of a wall or a larger
#: surface behind the board, fitted with the board's rectangle, shows none or one.
HIDDEN_EDGES = 3
#: How far a partly hidden candidate's in-plane rotation may differ from the chosen one's (mod
#: the rectangle's half turn) to be its rival, rad: "the board is the hidden one" then asks
#: no more of the unit's mount than "the board is the one that passed" does. A rectangle
#: turned a quarter turn from it (a box's face behind the board on the twin's random scenes)
#: would have the unit rolled by 90 deg; a mount is within degrees of its nominal.
HIDDEN_ROLL = math.radians(10.0)
#: How far in front of a candidate's rectangle another's returns must lie to hide it, m (a
#: panel a few cm before a board reads as the board's own surface; the distractors in front
#: of a board stand 0.5 m and more before it).
HIDDEN_GAP = 0.2


@dataclass(frozen=True)
class Candidate:
    """One board-like object of the search, fitted as the board (on the first scan)."""

    index: int  # 0: the search's first choice; k: its k-th runner-up
    returns: np.ndarray  # indices into the scan of the search's returns for it
    score: float  # the search's likeness (`align.search.board.board_score`), nan: unscored
    estimate: PoseEstimate  # the fit of one scan with this candidate as the board

    @property
    def passed(self) -> bool:
        return self.estimate.success

    def centre(self) -> np.ndarray | None:
        """The fitted board's centre in the LiDAR's frame {L}, m (None: no pose)."""
        pose = self.estimate.pose
        return None if pose is None else board_centre(pose.as_array())


def goodness(est: PoseEstimate) -> float:
    """g(z): the fit's one-sided log-density of its chi-square (module docstring); -inf for an
    estimate without a fit."""
    diag = est.diagnostics
    chi2_dof, dof = diag.get("chi2_per_dof"), diag.get("dof")
    if chi2_dof is None or not dof:
        return -math.inf
    z = (chi2_dof - 1.0) * math.sqrt(dof / 2.0)
    return -0.5 * max(z, 0.0) ** 2


def size_log_ratio(est: PoseEstimate) -> float:
    """log of the Savage-Dickey ratio for "the object is the known size" against "a flat
    rectangle of any size": the density of the size the rays see at the size given, over a
    uniform prior of `SIZE_RANGE` on each of width and height. Large for a board whose rays
    pin its size at the one given; about 0 or below for an object seen too obliquely, or too
    partly, to say its size; very negative for one of another size. 0 without a size seen."""
    diag = est.diagnostics
    d2, sw, sh = (diag.get(k) for k in ("size_mismatch_d2", "seen_width_std_m",
                                        "seen_height_std_m"))
    if d2 is None or not sw or not sh:
        return 0.0
    return -0.5 * d2 - math.log(2 * math.pi * sw * sh) + 2 * math.log(SIZE_RANGE)


def region_log_prior(centre: np.ndarray | None, hints: Hints) -> float:
    """log prior of a board at ``centre`` ({L}, m) under what the user and the station say:
    the expected distance (a Gaussian of `DISTANCE_SIGMA`, -inf beyond
    `DISTANCE_REFUSED_SIGMAS`) and the station's region (0 without one, -inf beyond its
    radius)."""
    if centre is None:
        return -math.inf if placed(hints) else 0.0
    out = 0.0
    if hints.expected_distance is not None:
        z = (float(np.linalg.norm(centre)) - hints.expected_distance) / DISTANCE_SIGMA
        if abs(z) > DISTANCE_REFUSED_SIGMAS:
            return -math.inf
        out -= 0.5 * z**2
    if hints.board_region is None:
        return out
    where, radius = hints.board_region
    off = float(np.linalg.norm(centre - np.asarray(where, dtype=float)))
    if off > radius:
        return -math.inf
    return out - 0.5 * (off * REGION_SIGMAS / radius) ** 2


def placed(hints: Hints) -> bool:
    """Whether the user or the station says where the board is (a region or a distance), so
    that a candidate can be refused for where it is."""
    return hints.board_region is not None or hints.expected_distance is not None


def hidden_board(c: Candidate) -> bool:
    """Whether a candidate that failed may be the board partly hidden (`HIDDEN_SHARE`): rays
    blocked in front of it, at most that share of its hits outside its rectangle,
    `HIDDEN_EDGES` of its edges seen, its fit sound, the board's size not refused."""
    e = c.estimate
    if e.status != Status.PARTIAL_BOARD or e.pose is None:
        return False
    d = e.diagnostics
    hits = max(float(d.get("hits", 0)), 1.0)
    return (d.get("occluded_rays", 0) > HIDDEN_SHARE * hits
            and d.get("outside_hits", math.inf) <= HIDDEN_SHARE * hits
            and d.get("chi2_per_dof", math.inf) <= 3.0
            and len(d.get("edges_seen", "")) >= HIDDEN_EDGES
            # the rays do not refuse the board's size for it (`align.fit.size`): a box's
            # face behind the board, partly hidden by it, is another size along an edge seen
            and not d.get("size_freed", False))


@dataclass(frozen=True)
class Decision:
    """What `decide` found: the chosen candidate (None: none passed, or none in the region),
    the runner-up it was weighed against, log10 of their likelihood ratio, and whether the
    choice is decisive (`DECISIVE_LR`); ``hidden``: the runner-up is a candidate partly
    hidden (`hidden_board`), weighed on the priors alone."""

    chosen: Candidate | None
    runner_up: Candidate | None
    log10_lr: float
    decisive: bool
    outside_region: tuple[Candidate, ...]  # candidates that passed but lie beyond the region
    hidden: bool = False


def weigh(c: Candidate, hints: Hints) -> float:
    """A candidate's log weight: its goodness, its size's log ratio and the region's log
    prior."""
    return (goodness(c.estimate) + size_log_ratio(c.estimate)
            + region_log_prior(c.centre(), hints))


def decide(candidates: list[Candidate], hints: Hints,
           hides: Callable[[Candidate, Candidate], bool] | None = None) -> Decision:
    """The candidate to report as the board (module docstring). ``hides(front, behind)``:
    whether ``front``'s returns lie in front of ``behind``'s rectangle (`HIDDEN_GAP` or more),
    hiding part of it (`align.api._hides`); None: no candidate is taken as hidden."""
    passed = [c for c in candidates if c.passed]
    outside = tuple(c for c in passed if placed(hints)
                    and region_log_prior(c.centre(), hints) == -math.inf)
    inside = [c for c in passed if c not in outside]
    if not inside:
        return Decision(None, None, math.nan, False, outside)
    weights = [weigh(c, hints) for c in inside]
    order = sorted(range(len(inside)), key=lambda i: -weights[i])  # ties: the search's order
    chosen = inside[order[0]]
    rival = _hidden_rival(chosen, candidates, hints, hides) if hides is not None else None
    if rival is not None:
        return rival
    if len(inside) == 1:
        return Decision(chosen, None, math.inf, True, outside)
    runner = inside[order[1]]
    log_lr = weights[order[0]] - weights[order[1]]
    return Decision(chosen, runner, log_lr / math.log(10.0), log_lr >= math.log(DECISIVE_LR),
                    outside)


def _alike(a: Candidate, b: Candidate) -> bool:
    """Whether two candidates' rectangles are turned alike in their planes (`HIDDEN_ROLL`,
    modulo a half turn: a rectangle's symmetry)."""
    d = a.estimate.pose.roll - b.estimate.pose.roll
    return abs((d + math.pi / 2) % math.pi - math.pi / 2) <= HIDDEN_ROLL


def _hidden_rival(chosen: Candidate, candidates: list[Candidate], hints: Hints,
                  hides: Callable[[Candidate, Candidate], bool]) -> Decision | None:
    """An undecided `Decision` when a candidate partly hidden by ``chosen`` (`hidden_board`,
    ``hides``) may be the board as well: the rays cannot say which (a board hidden behind a
    panel of its own size looks like a panel in front of a board), so only the priors can, by
    `DECISIVE_LR`; None when none is, or the priors put the chosen one decisively first."""
    prior = region_log_prior(chosen.centre(), hints)
    for c in candidates:
        if (c is chosen or c.passed or not hidden_board(c) or not _alike(chosen, c)
                or not hides(chosen, c)):
            continue
        log_lr = prior - region_log_prior(c.centre(), hints)
        if log_lr < math.log(DECISIVE_LR):
            return Decision(chosen, c, log_lr / math.log(10.0), False, (), hidden=True)
    return None

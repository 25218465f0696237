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
  Gaussian of `DISTANCE_SIGMA`) and the station's region (`Hints.board_region`: a Gaussian of
  a third of its radius about its centre; a candidate beyond the radius is refused outright).

The best candidate is chosen when its ratio over every other that passed is at least
`DECISIVE_LR`; otherwise the choice is ambiguous and no pose is reported. Two identical
panels side by side are ambiguous by construction (only a prior can tell them apart), as they
should be: a confident choice between them would be a coin toss.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from align.result import Hints, PoseEstimate

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
        if pose is None:
            return None
        r = pose.rotation()
        return -r.T @ np.array([pose.x, pose.y, pose.z])


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
    the expected distance (a Gaussian of `DISTANCE_SIGMA`) and the station's region (0 without
    one, -inf beyond its radius)."""
    if centre is None:
        return -math.inf if hints.board_region is not None else 0.0
    out = 0.0
    if hints.expected_distance is not None:
        out -= 0.5 * ((float(np.linalg.norm(centre)) - hints.expected_distance)
                      / DISTANCE_SIGMA) ** 2
    if hints.board_region is None:
        return out
    where, radius = hints.board_region
    off = float(np.linalg.norm(centre - np.asarray(where, dtype=float)))
    if off > radius:
        return -math.inf
    return out - 0.5 * (off * REGION_SIGMAS / radius) ** 2


@dataclass(frozen=True)
class Decision:
    """What `decide` found: the chosen candidate (None: none passed, or none in the region),
    the runner-up it was weighed against, log10 of their likelihood ratio, and whether the
    choice is decisive (`DECISIVE_LR`)."""

    chosen: Candidate | None
    runner_up: Candidate | None
    log10_lr: float
    decisive: bool
    outside_region: tuple[Candidate, ...]  # candidates that passed but lie beyond the region


def weigh(c: Candidate, hints: Hints) -> float:
    """A candidate's log weight: its goodness, its size's log ratio and the region's log
    prior."""
    return (goodness(c.estimate) + size_log_ratio(c.estimate)
            + region_log_prior(c.centre(), hints))


def decide(candidates: list[Candidate], hints: Hints) -> Decision:
    """The candidate to report as the board (module docstring)."""
    passed = [c for c in candidates if c.passed]
    outside = tuple(c for c in passed if hints.board_region is not None
                    and region_log_prior(c.centre(), hints) == -math.inf)
    inside = [c for c in passed if c not in outside]
    if not inside:
        return Decision(None, None, math.nan, False, outside)
    weights = [weigh(c, hints) for c in inside]
    order = sorted(range(len(inside)), key=lambda i: -weights[i])  # ties: the search's order
    chosen = inside[order[0]]
    if len(inside) == 1:
        return Decision(chosen, None, math.inf, True, outside)
    runner = inside[order[1]]
    log_lr = weights[order[0]] - weights[order[1]]
    return Decision(chosen, runner, log_lr / math.log(10.0), log_lr >= math.log(DECISIVE_LR),
                    outside)

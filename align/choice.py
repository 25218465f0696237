"""The board's choice among the search's candidates: each fitted as the board, judged on the same
terms, the best chosen by a stated likelihood ratio (`decide`).

The board search (`align.search.board`) ranks candidates by a cheap likeness (count,
reflectivity, how a rectangle of the board's size holds them). That ranking picked a
background surface 2.9 m beside the board on a real scan, and the fit then passed: the fit of
a wrong object can pass every check of its own. What tells the board apart is how well the
known rectangle explains each candidate's rays, side by side: the range residuals and the
hit/miss labels of every ray near its edges, pooled in the fit's chi-square.

The statistic. Under "candidate c is the board" the fit's residuals are the model's, so its
chi-square D_c over k_c degrees of freedom is about chi2(k_c): z_c = (D_c - k_c) / sqrt(2 k_c)
is about N(0, 1). What the residuals of an object that is not the board look like is not
modelled (anything): its density is taken flat. The likelihood ratio of "a is the board"
against "b is" is then the ratio of the two candidates' goodness densities,

    log LR(a : b) = g(z_a) - g(z_b),   g(z) = -max(z, 0)^2 / 2,

one-sided: a fit better than its noise model (z < 0: the labels' blur set wider than this
scan's) is no evidence against the candidate. Each side is weighted by the station's prior
on where its board is (`Hints.board_region`): a Gaussian of the region's radius / 3 about its
centre, and a candidate beyond the radius is refused outright. The best candidate is chosen
when its ratio over every other that passed its own checks is at least `DECISIVE_LR`;
otherwise the choice is ambiguous and no pose is reported. Two identical panels side by side
are ambiguous by construction (only a prior can tell them apart), as they should be: a
confident choice between them would be a coin toss. Of two panels the data cannot tell, a
ratio of `DECISIVE_LR` arises by chance once in about 10,000 pairs (z > 3.7).
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


def region_log_prior(centre: np.ndarray | None, hints: Hints) -> float:
    """log prior of a board at ``centre`` ({L}, m) under the station's region: 0 without one,
    -inf beyond its radius."""
    if hints.board_region is None:
        return 0.0
    if centre is None:
        return -math.inf
    where, radius = hints.board_region
    off = float(np.linalg.norm(centre - np.asarray(where, dtype=float)))
    if off > radius:
        return -math.inf
    return -0.5 * (off * REGION_SIGMAS / radius) ** 2


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
    """A candidate's log weight: its goodness plus the region's log prior."""
    return goodness(c.estimate) + region_log_prior(c.centre(), hints)


def decide(candidates: list[Candidate], hints: Hints) -> Decision:
    """The candidate to report as the board (module docstring)."""
    passed = [c for c in candidates if c.passed]
    outside = tuple(c for c in passed if region_log_prior(c.centre(), hints) == -math.inf)
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

"""A new unit's own range errors on the real twin (MuJoCo, packets' ranges): a common offset
estimated with the pose, per-laser offsets carried in the covariance, honest sigmas over many
poses; and the twin's random scenes."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest

import align
from scenarios.study.protocol import pose_errors, random_pose
from twin.sim.bench import BenchSim
from twin.sim.emulation import EmulationConfig
from twin.sim.params import CLUTTER_GEOM_PREFIX, HOLDER_GEOM_PREFIX, BenchParams, random_scene

SHARP = {"edge_tolerance": (0.0, 0.0)}
#: The datasheet's +-30 mm as a uniform's 1-sigma, m.
DATASHEET = 0.030 / np.sqrt(3.0)


def _scans(rng: np.random.Generator, n: int, **noise) -> tuple[list, BenchSim]:
    # the sharp beam the estimator is told (`SHARP`), as bench_align --offsets has it: the
    # twin's default divergent beam returns from the board up to a footprint beyond its edges,
    # hits a zero tolerance takes as certain (fused, 1-100 um past an edge pinned the offset's
    # band 1 mm off at 3.4 sigma)
    params, x, yaw = random_pose(rng)
    sim = BenchSim(params, seed=int(rng.integers(2**31)),
                   noise=EmulationConfig(laser_offset_sigma=0.0, divergence=False, **noise))
    sim.move_to(x_m=x, yaw_rad=np.deg2rad(yaw))
    return [sim.scan() for _ in range(n)], sim


@pytest.fixture(autouse=True)
def _quiet():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield


def test_twin_draws_a_units_offsets_from_a_seed():
    cfg = EmulationConfig(range_bias_spread=0.005, laser_offset_spread=0.005)
    a = BenchSim(BenchParams(), seed=4, noise=cfg).emulator
    b = BenchSim(BenchParams(), seed=4, noise=cfg).emulator
    c = BenchSim(BenchParams(), seed=5, noise=cfg).emulator
    assert a.range_bias == b.range_bias != c.range_bias
    assert abs(a.range_bias) <= 0.005 and np.all(np.abs(a.laser_offsets) <= 0.005)
    np.testing.assert_array_equal(a.laser_offsets, b.laser_offsets)
    assert np.ptp(a.laser_offsets) > 0.002  # uniform over +-5 mm, not one value
    # the default draws nothing more: a seed's stream is what it was
    d = BenchSim(BenchParams(), seed=4, noise=EmulationConfig(range_bias=0.002)).emulator
    assert d.range_bias == 0.002


def test_a_30_mm_offset_is_recovered_and_does_not_move_the_pose():
    rng = np.random.default_rng(21)
    for _ in range(2):
        scans, sim = _scans(rng, 10, range_bias=-0.030)
        truth = scans[0].meta["truth_pose"]
        est = align.estimate(scans, hints=align.Hints(**SHARP,
                                                      range_offset_prior=(0.0, DATASHEET)))
        assert est.success, est.diagnostics.get("reason")
        b, b_sd = est.diagnostics["range_offset_m"], est.diagnostics["range_offset_std_m"]
        assert abs(b - sim.emulator.range_bias) < max(4 * b_sd, 1e-3) and b_sd < 2e-3
        e, sd = pose_errors(est, truth)
        assert np.all(np.abs(e[[0, 3, 4, 5]]) < 4 * sd[[0, 3, 4, 5]]), (e, sd)
        # taken as zero, the same offset moves yaw or x beyond their sigmas (the fault this
        # fixes)
        naive = align.estimate(scans, hints=align.Hints(**SHARP))
        e0, sd0 = pose_errors(naive, truth)
        assert max(abs(e0[5]) / sd0[5], abs(e0[0]) / sd0[0]) > 2


def test_a_new_unit_has_its_offset_estimated_by_default():
    """The shipped station (and so the command line without one) takes a unit as new: its
    common offset estimated with the datasheet's prior; a range calibration applied, or an
    offset stated as known (std 0), is not estimated (issue 34)."""
    from scenarios.station import Station

    st = Station()
    assert st.estimate_hints().range_offset_prior == pytest.approx((0.0, DATASHEET))
    assert st.estimate_hints(calibrated=True).range_offset_prior is None
    hdl = Station.model_validate({"sensor": {"model": "HDL-32E"}})
    assert hdl.estimate_hints().range_offset_prior[1] == pytest.approx(0.02 / np.sqrt(3.0))
    known = Station.model_validate({"sensor": {"range_offset_mm": -30.0,
                                               "range_offset_std_mm": 0.0}})
    b, b_sd = known.estimate_hints().range_offset_prior
    assert b == pytest.approx(-0.03) and b_sd < 1e-4
    scans, sim = _scans(np.random.default_rng(22), 10, range_bias=-0.030)
    est = align.estimate(scans, hints=replace(st.estimate_hints(), **SHARP))
    assert est.success, est.diagnostics.get("reason")
    e, sd = pose_errors(est, scans[0].meta["truth_pose"])
    assert np.all(np.abs(e[[0, 3, 4, 5]]) < 4 * sd[[0, 3, 4, 5]]), (e, sd)
    assert abs(est.diagnostics["range_offset_m"] - sim.emulator.range_bias) < 2e-3


def test_a_ring_grazing_the_top_edge_near_a_corner_holds_the_fits_height():
    """Traced on `bench_align.py --offsets --poses 160` (pose 120): rolled 0.9 deg and tilted
    2.6, the board's top ring crosses its top edge 10 cm from a corner. Fused 50 scans of a unit
    30 mm short, that crossing was left out as a corner at the right height and taken for the
    side edge from a start 3 cm low (then dropped as gross); nothing else held z, every fit
    settled 32 mm low with 426 misses inside its rectangle, the posterior found nothing, and
    the offset came out 12.7 mm off (`align.fit.bracket_kernels.grazes_top_or_bottom`)."""
    params = BenchParams.from_edge(roll_deg=0.9084134270754474, tilt_deg=2.5792125117846156,
                                   yaw_deg=-0.5305904053419566, lever_arm_mm=(0.0, 0.0, 60.0))
    sim = BenchSim(params, seed=1038096735, noise=EmulationConfig(
        laser_offset_sigma=0.0, divergence=False, range_bias=-0.030))
    sim.move_to(x_m=0.0054805518984158255, yaw_rad=0.0)
    scans = [sim.scan() for _ in range(50)]
    est = align.estimate(scans, hints=align.Hints(**SHARP, range_offset_prior=(0.0, DATASHEET)))
    assert est.success, est.diagnostics.get("reason")
    assert est.diagnostics["label_posterior"] and est.diagnostics["inside_misses"] == 0
    assert abs(est.diagnostics["range_offset_m"] + 0.030) < 0.002
    e, _ = pose_errors(est, scans[0].meta["truth_pose"])
    assert np.all(np.abs(e[3:]) < np.deg2rad(0.05)) and abs(e[2]) < 0.005, e


def _offset_chi2(rng: np.random.Generator, units: int, scans: int, axes: list[int]
                 ) -> np.ndarray:
    """Mean squared z of the pose's ``axes`` and of the offset, over ``units`` twin units each
    with its own common offset uniform within +-5 mm (the prior saying so), ``scans`` fused."""
    hints = align.Hints(**SHARP, range_offset_prior=(0.0, 0.005 / np.sqrt(3.0)))
    z2, failed = [], 0
    for _ in range(units):
        group, sim = _scans(rng, scans, range_bias_spread=0.005)
        est = align.estimate(group, hints=hints)
        if not est.success:  # counted: a failed estimate reports no sigma to check
            failed += 1
            continue
        e, sd = pose_errors(est, group[0].meta["truth_pose"])
        db = est.diagnostics["range_offset_m"] - sim.emulator.range_bias
        z2.append(np.append((e / sd)[axes], db / est.diagnostics["range_offset_std_m"]) ** 2)
    assert failed <= 0.01 * units, failed
    return np.mean(z2, axis=0)


def test_offset_sigmas_are_honest_over_many_units():
    # chi-square of every reported sigma (pose and offset), units drawn uniform within +-5 mm,
    # the prior saying so; 14 poses x 5 scans fused: a loose band for that sample
    chi2 = _offset_chi2(np.random.default_rng(22), 14, 5, [0, 1, 3, 4, 5])
    assert np.all((chi2 > 0.3) & (chi2 < 2.2)), chi2


@pytest.mark.slow
def test_offset_sigmas_are_honest_over_120_units_fused_10():
    # issue 21's check at a size that tells an honest covariance from the one before the joint
    # profile (yaw chi2 1.6-1.8, x 1.5-1.7, roll 0.7): 120 units uniform within +-5 mm, the
    # prior saying so, 10 scans fused, the sharp beam. One axis's chi2 over 120 units has a sd
    # of about 0.13: the bands are 3 of them about 1. (Over 40 units, 0.22, its old bands were
    # within two; they held while the twin's beam was divergent against the sharp beam the
    # estimator was told, which moved every figure)
    chi2 = _offset_chi2(np.random.default_rng(24), 120, 10, [4, 3, 5, 0])  # tilt roll yaw x b
    assert np.all((chi2 > 0.6) & (chi2 < 1.4)), chi2
    assert 0.7 < np.mean(chi2[2:4]) < 1.35, chi2


def test_per_laser_offsets_uncalibrated_are_in_tilts_sigma():
    rng = np.random.default_rng(23)
    modelled = align.Hints(**SHARP, laser_offset_sigma=0.005 / np.sqrt(3.0))
    z_m, z_n = [], []
    for _ in range(10):
        scans, _ = _scans(rng, 5, laser_offset_spread=0.005)
        truth = scans[0].meta["truth_pose"]
        for hints, out in ((modelled, z_m), (align.Hints(**SHARP), z_n)):
            est = align.estimate(scans, hints=hints)
            assert est.success, est.diagnostics.get("reason")
            e, sd = pose_errors(est, truth)
            out.append((e[4] / sd[4]) ** 2)
    assert 0.3 < np.mean(z_m) < 2.0, np.mean(z_m)
    assert np.mean(z_n) > 3 * np.mean(z_m)  # taken as none, tilt's sigma does not cover it


def test_random_scenes_put_nothing_in_front_of_the_board():
    # a turned box's corner reaches further along Y than its half size: every corner of every
    # piece of clutter stands behind the board's face (an occluder in front is another test)
    by = BenchParams().board_position[1]
    for seed in range(200):
        for box in random_scene(np.random.default_rng(seed)).clutter:
            c, s = np.cos(box.yaw), np.sin(box.yaw)
            ys = [box.pos[1] + a * box.size[0] * s + b * box.size[1] * c
                  for a in (-1, 1) for b in (-1, 1)]
            assert min(ys) > by + 0.019, (seed, box)


def test_random_scenes_are_seeded_named_and_scanned():
    a = random_scene(np.random.default_rng(3))
    assert a == random_scene(np.random.default_rng(3)) != random_scene(np.random.default_rng(4))
    assert random_scene(np.random.default_rng(3), max_holders=0).clutter == a.clutter
    params = BenchParams(wall_distance=0.9, stand_offset=0.25, holders=a.holders or
                         random_scene(np.random.default_rng(5)).holders, clutter=a.clutter)
    model = params.build_model()
    assert model.geom("wall").pos[1] == pytest.approx(0.9)
    for prefix, boxes in ((HOLDER_GEOM_PREFIX, params.holders),
                          (CLUTTER_GEOM_PREFIX, params.clutter)):
        for i, box in enumerate(boxes):
            g = model.geom(f"{prefix}{i}")
            assert params.geom_reflectivity(model)[g.id] == pytest.approx(box.reflectivity)
    with pytest.raises(ValueError):
        BenchParams(wall_distance=0.0)
    # a scan of the scene: the wall's returns where it now stands
    sim = BenchSim(BenchParams(wall_distance=0.9), seed=1,
                   noise=EmulationConfig.ideal(quantise=False))
    s = sim.scan()
    far = s.y[(s.distance > 0) & (np.abs(s.x) < 0.2) & (s.z > 0.3)]
    assert far.size and np.max(far) == pytest.approx(2.5 + 0.9, abs=0.05)

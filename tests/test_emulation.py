"""VLP-16 emulation: geometry against an independent ray/plane calculation, the fast paths
against brute-force MuJoCo rays, and the measurement model statistically."""

from __future__ import annotations

import math

import numpy as np
import pytest
from twin_analytic import board_intersections

from twin.core import vlp16
from twin.core.scan import ReturnType
from twin.sim.bench import BenchSim, raykernel
from twin.sim.emulation import EmulationConfig, VLP16Emulator, _gaussian
from twin.sim.params import BenchParams

W, H = 0.90, 0.54


def _grid(n_seq: int = 1800, rpm: float = 600.0, phase: float = 0.3) -> np.ndarray:
    seq = np.repeat(np.arange(n_seq), 16)
    lid = np.tile(np.arange(16), n_seq)
    t = seq * vlp16.SEQUENCE_PERIOD + lid * vlp16.LASER_PERIOD
    return np.mod(phase + t * rpm / 60 * 2 * np.pi, 2 * np.pi).reshape(-1, 16)


def _edge_margin(pose, scan, margin: float = 0.005) -> np.ndarray:
    """Firings whose ray meets the board plane within ``margin`` of an edge (ambiguous: the
    3 mm plate's side faces, which the analytic plane does not have)."""
    _, on_in = board_intersections(pose, scan.azimuth, scan.laser_id, W - 2 * margin,
                                   H - 2 * margin)
    _, on_out = board_intersections(pose, scan.azimuth, scan.laser_id, W + 2 * margin,
                                    H + 2 * margin)
    return on_out & ~on_in


@pytest.mark.parametrize("case", range(4))
def test_ideal_returns_lie_on_the_analytic_board_intersection(case: int) -> None:
    rng = np.random.default_rng(case)
    params = BenchParams.from_edge(roll_deg=rng.uniform(-3, 3), tilt_deg=rng.uniform(-3, 3),
                                   yaw_deg=rng.uniform(-3, 3))
    sim = BenchSim(params, seed=case, noise=EmulationConfig.ideal())
    sim.move_to(x_m=rng.uniform(-0.05, 0.05), yaw_rad=math.radians(rng.uniform(-10, 10)))
    scan = sim.scan()
    pose = scan.meta["truth_pose"]
    rng_a, on = board_intersections(pose, scan.azimuth, scan.laser_id, W, H)
    assert on.sum() > 400
    # Every analytic board hit returned, within the 2 mm quantisation (rounding: 1 mm).
    assert np.all(scan.distance[on] > 0)
    assert np.max(np.abs(scan.distance[on] - rng_a[on])) <= vlp16.DISTANCE_UNIT / 2 + 1e-9
    # Per-laser counts: firings whose scan point lies on the board plane, away from the edges.
    amb = _edge_margin(pose, scan)
    p_o = pose.transform(scan.xyz)
    scan_on = (scan.valid & (np.abs(p_o[:, 1]) < 0.002) & (np.abs(p_o[:, 0]) <= W / 2 + 0.01)
               & (np.abs(p_o[:, 2]) <= H / 2 + 0.01))
    count_a = np.bincount(scan.laser_id[on & ~amb], minlength=16)
    count_s = np.bincount(scan.laser_id[scan_on & ~amb], minlength=16)
    np.testing.assert_array_equal(count_s, count_a)
    assert amb.sum() < 0.1 * on.sum()
    # About six rings on a 0.54 m board at 2.5 m (2 deg spacing).
    assert 5 <= len(np.unique(scan.ring[on])) <= 7


def test_board_size_and_pose_are_bench_parameters() -> None:
    """A bigger board, moved and turned on its stand: the geometry still matches the analytic
    intersection in the (true) board frame, and the truth reflects the board's pose."""
    params = BenchParams(board_width=1.2, board_height=0.6, board_position=(0.05, 0.1, 0.52),
                         board_yaw=math.radians(4), board_tilt=math.radians(-2))
    sim = BenchSim(params, seed=0, noise=EmulationConfig.ideal())
    scan = sim.scan()
    pose = scan.meta["truth_pose"]
    assert math.degrees(pose.yaw) == pytest.approx(-4.0, abs=0.2)
    rng_a, on = board_intersections(pose, scan.azimuth, scan.laser_id, 1.2, 0.6)
    assert on.sum() > 600
    assert np.max(np.abs(scan.distance[on] - rng_a[on])) <= vlp16.DISTANCE_UNIT / 2 + 1e-9


def test_background_reflectivity_sets_the_walls_intensity() -> None:
    for refl in (0.2, 0.6):
        sim = BenchSim(BenchParams(background_reflectivity=refl), seed=0,
                       noise=EmulationConfig.ideal())
        scan = sim.scan()
        pose = scan.meta["truth_pose"]
        p_o = pose.transform(scan.xyz)
        wall = scan.valid & (np.abs(p_o[:, 1] - 1.5) < 0.01) & (p_o[:, 2] > -0.45)  # not floor
        d_o = scan.directions()[wall] @ pose.rotation().T
        np.testing.assert_allclose(scan.intensity[wall], np.rint(100 * refl * d_o[:, 1]),
                                   atol=1)
        assert wall.sum() > 100


def test_the_nominal_bench_puts_six_rings_on_the_board() -> None:
    sim = BenchSim(seed=0, noise=EmulationConfig.ideal())
    scan = sim.scan()
    _, on = board_intersections(scan.meta["truth_pose"], scan.azimuth, scan.laser_id, W, H)
    np.testing.assert_array_equal(np.unique(vlp16.ELEVATION_DEG[scan.laser_id[on]]),
                                  [-5, -3, -1, 1, 3, 5])


@pytest.mark.parametrize("divergence", [False, True])
def test_fast_paths_equal_brute_force_mujoco_rays(divergence: bool) -> None:
    """Culling + analytic planes (grid path) and the generic per-firing path both equal one
    plain mj_multiRay per origin, ray for ray."""
    params = BenchParams.from_edge(roll_deg=1.0, tilt_deg=-2.0, yaw_deg=1.5)
    cfg = EmulationConfig.ideal(quantise=False, divergence=divergence)
    sims = [BenchSim(params, seed=1, noise=cfg.with_(culling=c)) for c in (True, False)]
    for sim in sims:
        sim.set_stage_positions(x_m=0.03, yaw_rad=math.radians(-7))
    # Three rotations in one grid: the culling must follow the azimuth round more than once.
    az = _grid(1000 if divergence else 5400)
    lid = np.tile(np.arange(16, dtype=np.uint8), len(az))
    p, r = sims[0].physics.lidar_pose_world()
    grid = sims[0].emulator.fire_grid(az, p, r)
    generic = sims[0].emulator.fire(az.reshape(-1), lid, p, r)
    brute = sims[1].emulator.fire(az.reshape(-1), lid, p, r)
    # the grid path without culling (every row through MuJoCo) too: it once failed with
    # divergence on, the sub-ray pass reading intervals only the culling had made
    unculled = sims[1].emulator.fire_grid(az, p, r)
    np.testing.assert_allclose(unculled.distance, brute.distance, rtol=0, atol=1e-9)
    np.testing.assert_allclose(grid.distance, brute.distance, rtol=0, atol=1e-9)
    np.testing.assert_allclose(generic.distance, brute.distance, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(grid.intensity, brute.intensity)
    assert (brute.distance > 0).sum() > 0.5 * len(lid)


def test_fire_grid_draws_the_same_noise_as_fire() -> None:
    """The measurement model consumes the generator in firing order, one noise word per
    firing whether it returns or not: the fast grid path and the generic per-firing path give
    the same noisy returns for the same seed, and leave the generator in the same state."""
    cfg = EmulationConfig(divergence=False, detection_threshold=3e-3)  # many dropouts too
    sims = [BenchSim(seed=7, noise=cfg) for _ in range(2)]
    az = _grid(1800)
    lid = np.tile(np.arange(16, dtype=np.uint8), len(az))
    p, r = sims[0].physics.lidar_pose_world()
    grid = sims[0].emulator.fire_grid(az, p, r)
    generic = sims[1].emulator.fire(az.reshape(-1), lid, p, r)
    valid = grid.distance > 0
    assert 0.3 < valid.mean() < 0.55  # returns, misses and dropouts (0.58 without)
    np.testing.assert_array_equal(grid.distance, generic.distance)
    np.testing.assert_array_equal(grid.intensity, generic.intensity)
    np.testing.assert_array_equal(grid.return_type, generic.return_type)
    assert sims[0].rng.random() == sims[1].rng.random()


@pytest.mark.parametrize("x, yaw_deg, roll_deg, tilt_deg", [
    (-0.05, -30, 4, 5), (0.05, 30, -4, -5), (0.0, 12, 0, 8), (0.02, -20, 10, -3)])
def test_culling_is_exact_over_the_travel(x, yaw_deg, roll_deg, tilt_deg) -> None:
    """The culling bounds (spheres, box corners' azimuths and elevations, the wall's extent)
    never drop a ray MuJoCo would return, at the stages' extremes and with tilted mounts."""
    params = BenchParams.from_edge(roll_deg=roll_deg, tilt_deg=tilt_deg, yaw_deg=-1.0)
    cfg = EmulationConfig.ideal(quantise=False)
    sims = [BenchSim(params, seed=2, noise=cfg.with_(culling=c)) for c in (True, False)]
    for sim in sims:
        sim.set_stage_positions(x_m=x, yaw_rad=math.radians(yaw_deg))
    az = _grid(1800, phase=1.0)
    p, r = sims[0].physics.lidar_pose_world()
    fast = sims[0].emulator.fire_grid(az, p, r)
    brute = sims[1].emulator.fire_grid(az, p, r)
    np.testing.assert_allclose(fast.distance, brute.distance, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(fast.intensity, brute.intensity)


def test_moving_origins_are_cast_exactly() -> None:
    """Per-firing origins (a moving sensor) share mj_multiRay calls within 0.2 mm and are then
    corrected on the face they hit: equal to one ray per origin."""
    sim = BenchSim(seed=0, noise=EmulationConfig.ideal(quantise=False))
    p, r = sim.physics.lidar_pose_world()
    rng = np.random.default_rng(3)
    n = 4000
    az = rng.uniform(0, 2 * np.pi, n)
    lid = rng.integers(0, 16, n).astype(np.uint8)
    pos = p + rng.uniform(-1e-3, 1e-3, (n, 3))
    rot = np.repeat(r[None], n, axis=0)
    got = sim.emulator.fire(az, lid, pos, rot)
    origins, dirs = sim.emulator.rays(az, lid, pos, rot)
    want = np.array([sim.caster.multiray(o, d[None])[0][0] for o, d in zip(origins, dirs,
                                                                              strict=True)])
    want = np.where(np.isfinite(want) & (want >= vlp16.RANGE_MIN), want, 0.0)
    # Castor spheres are the only curved faces: allow 0.2 mm there, exact elsewhere.
    np.testing.assert_allclose(got.distance[0], want, rtol=0, atol=2e-4)
    assert np.mean(np.abs(got.distance[0] - want) < 1e-9) > 0.99


def test_range_noise_has_the_configured_mean_and_sigma() -> None:
    offsets = tuple(np.linspace(-0.004, 0.004, 16))
    cfg = EmulationConfig(divergence=False, dropouts=False, rpm_wander_sigma=0.0,
                          range_noise_sigma=0.014, laser_offsets=offsets, range_bias=0.001)
    sim = BenchSim(seed=11, noise=cfg)
    res, lids = [], []
    for scan in sim.scans(12):
        rng_a, on = board_intersections(scan.meta["truth_pose"], scan.azimuth, scan.laser_id,
                                        W - 0.02, H - 0.02)
        res.append(scan.distance[on] - rng_a[on])
        lids.append(scan.laser_id[on])
    res = np.concatenate(res)
    lids = np.concatenate(lids)
    expected_mean = 0.001 + np.asarray(offsets)[lids]
    centred = res - expected_mean
    n = len(res)
    assert n > 5000
    sigma = math.hypot(0.014, vlp16.DISTANCE_UNIT / math.sqrt(12))
    assert abs(centred.mean()) < 4 * sigma / math.sqrt(n)
    assert centred.std() == pytest.approx(sigma, rel=0.05)
    # The per-laser offsets come out per laser.
    for lid in np.unique(lids):
        m = lids == lid
        assert res[m].mean() == pytest.approx(0.001 + offsets[lid],
                                              abs=5 * sigma / math.sqrt(m.sum()))


def test_default_laser_offsets_are_a_few_mm_and_seeded() -> None:
    a = BenchSim(seed=5).emulator.laser_offsets
    b = BenchSim(seed=5).emulator.laser_offsets
    np.testing.assert_array_equal(a, b)
    assert np.all(np.abs(a) <= 0.005) and np.any(a != 0)


def test_box_muller_noise_is_gaussian() -> None:
    x = _gaussian(np.random.default_rng(0), 200_001, 2.0)
    assert len(x) == 200_001
    assert x.mean() == pytest.approx(0, abs=0.02)
    assert x.std() == pytest.approx(2.0, rel=0.01)
    # Fourth moment of a Gaussian: 3 sigma^4.
    assert np.mean(x**4) / 16 == pytest.approx(3.0, rel=0.05)


def test_grid_sincos_is_exact() -> None:
    """The kernel's sines and cosines (a libm pair per 8 sequences, series for the rest) equal
    numpy's: on the sensor's grid with two sub-rays per firing (rows not at the same offset
    from the base), with jitter (rows not constant), and off the grid (libm); and the rows'
    offsets and their spread (what the culling widens its intervals by) are right."""
    az = _grid(300)
    rng = np.random.default_rng(0)
    row_laser = np.repeat(np.arange(16), 2)
    row_dh = np.tile([0.0, 1e-3], 16)
    no_planes = (np.zeros((0, 32, 17)), np.zeros((0, 32, 1, 2), dtype=np.int64),
                 np.zeros((0, 32), dtype=np.int64))
    for a in (az, az + rng.uniform(-1e-6, 1e-6, az.shape), rng.uniform(0, 2 * np.pi, az.shape)):
        base, d_first, spread = raykernel.grid_prepare(a, row_laser, row_dh)
        s, c, dist, cos_inc = (np.empty(32 * 300) for _ in range(4))
        gid = np.empty(32 * 300, np.int32)
        raykernel.grid_rays(a, row_laser, row_dh, *no_planes, 101.0, s, c, dist, cos_inc, gid)
        rays = a.T[row_laser] + row_dh[:, None]  # row-major, as the kernel lays them out
        np.testing.assert_allclose(s, np.sin(rays).reshape(-1), rtol=0, atol=2e-15)
        np.testing.assert_allclose(c, np.cos(rays).reshape(-1), rtol=0, atol=2e-15)
        assert np.all(np.isinf(dist)) and np.all(gid == -1)  # no planes: no hits
        np.testing.assert_array_equal(base, a[:, 0])
        d = (rays - base + np.pi) % (2 * np.pi) - np.pi
        np.testing.assert_allclose(d_first, d[:, 0], rtol=0, atol=1e-12)
        assert spread == pytest.approx(np.abs(d - d[:, :1]).max(), abs=1e-12)


def test_intensity_follows_reflectivity_and_incidence() -> None:
    cfg = EmulationConfig(divergence=False, dropouts=False, range_noise_sigma=0.0)
    bright = BenchSim(BenchParams(board_reflectivity=0.8), seed=1, noise=cfg).scan()
    dark = BenchSim(BenchParams(board_reflectivity=0.2), seed=1, noise=cfg).scan()
    means = []
    for scan in (bright, dark):
        _, on = board_intersections(scan.meta["truth_pose"], scan.azimuth, scan.laser_id,
                                    W - 0.02, H - 0.02)
        means.append(scan.intensity[on].astype(float).mean())
    assert means[0] / means[1] == pytest.approx(4.0, rel=0.1)
    # Ideal intensity: 100 x reflectivity x cos(incidence).
    ideal = BenchSim(BenchParams(board_reflectivity=0.8), seed=1,
                     noise=EmulationConfig.ideal()).scan()
    pose = ideal.meta["truth_pose"]
    _, on = board_intersections(pose, ideal.azimuth, ideal.laser_id, W - 0.02, H - 0.02)
    d_o = ideal.directions()[on] @ pose.rotation().T
    np.testing.assert_allclose(ideal.intensity[on], np.rint(80 * d_o[:, 1]), atol=1)


def test_dropouts_near_the_detection_threshold() -> None:
    # Threshold at the board's own return energy: about half the board returns drop.
    board_energy = 0.55 * 1.0 / 2.6**2
    cfg = EmulationConfig(divergence=False, detection_threshold=board_energy,
                          detection_softness=0.3)
    scan = BenchSim(seed=2, noise=cfg).scan()
    _, on = board_intersections(scan.meta["truth_pose"], scan.azimuth, scan.laser_id,
                                W - 0.02, H - 0.02)
    frac = scan.valid[on].mean()
    assert 0.2 < frac < 0.8
    assert BenchSim(seed=2, noise=cfg.with_(dropouts=False)).scan().valid[on].all()


def test_range_limits() -> None:
    scan = BenchSim(seed=0, noise=EmulationConfig.ideal(range_max=3.0, range_min=2.0)).scan()
    d = scan.distance[scan.valid]
    assert d.min() >= 2.0 and d.max() <= 3.0


def test_divergence_gives_mixed_and_dual_returns_at_the_board_edges() -> None:
    cfg = EmulationConfig.ideal(divergence=True, return_mode="dual")
    sim = BenchSim(seed=0, noise=cfg)
    scan = sim.scan()
    assert scan.return_mode == vlp16.RETURN_MODE_DUAL
    n = len(scan) // 2
    d = scan.distance.reshape(n, 2)
    rt = scan.return_type.reshape(n, 2)
    two = (d[:, 0] > 0) & (d[:, 1] > 0) & (np.abs(d[:, 0] - d[:, 1]) > 0.5)
    assert two.sum() > 10
    # Where two echoes come back, the first block is the last (farther) return.
    assert np.all(d[two, 0] > d[two, 1])
    assert np.all(rt[two, 0] & ReturnType.LAST)
    # Those whose near echo lies on the board sit at its edges (the far echo is the wall;
    # elsewhere, e.g. grazing the floor, long footprints split into echoes too).
    pose = scan.meta["truth_pose"]
    near = scan.select(np.flatnonzero(np.repeat(two, 2)))
    pts = pose.transform(near.xyz)[1::2]
    on_board = (np.abs(pts[:, 1]) < 0.01) & (np.abs(pts[:, 0]) < W / 2 + 0.02) & (
        np.abs(pts[:, 2]) < H / 2 + 0.02)
    assert on_board.sum() >= 4  # two vertical edges x six rings, footprint 2 of 3.5 mrad
    edge = np.minimum(np.abs(np.abs(pts[on_board, 0]) - W / 2),
                      np.abs(np.abs(pts[on_board, 2]) - H / 2))
    assert np.all(edge < 0.01)
    # Single echoes fill both blocks identically.
    one = (d[:, 0] > 0) & ~two
    np.testing.assert_array_equal(d[one, 0], d[one, 1])


def _side_edge_sweep(params: BenchParams, cfg: EmulationConfig, seed: int = 0
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every laser fired every 0.005 deg (0.09 mrad, far finer than the spin's 3.5 mrad) over
    azimuth -30..0 deg, across both side edges of the board at the stages' reference: (range
    m, intensity, points in {O} (N, 3) m) of the strongest returns."""
    sim = BenchSim(params, seed=seed, noise=cfg)
    az = np.repeat(np.deg2rad(np.arange(-30.0, 0.0, 0.005))[:, None], 16, axis=1)
    p, r = sim.physics.lidar_pose_world()
    out = sim.emulator.fire_grid(az, p, r)
    pts = sim.physics.lidar_pose_in_board().transform(
        np.column_stack((out.x[0], out.y[0], out.z[0])))
    return out.distance[0], out.intensity[0], pts


def test_returns_beyond_a_side_edge_are_a_divergent_beams_side_sub_ray() -> None:
    """A return at the board's range a few mm beyond a side edge, dim, is a beam whose centre
    misses the board while one horizontal sub-ray (weight 0.15, 1 mrad off) meets it: the
    board's echo (its own range, 0.15 of the board's intensity) and the background's are
    farther apart than the echo separation, and the strongest wins. With a far, dark wall
    (bench_align --scenes, pose 13: 2.15 m behind, 0.22) that is the board's; with the bench's
    wall (1.5 m, 0.30) the wall's. The sharp beam gives none; the twin's noise is on them as on
    every return (none is noise-free)."""
    far_dark = BenchParams(wall_distance=2.15, reflectivity_overrides={"wall": 0.22})

    def beyond(d: np.ndarray, pts: np.ndarray) -> np.ndarray:
        # on the board's plane, within its height, more than 0.3 mm beyond a side edge: the
        # 3 mm plate's side face itself returns at the edge (|x| = W / 2)
        return ((d > 0) & (np.abs(pts[:, 1]) < 0.01) & (np.abs(pts[:, 2]) < H / 2)
                & (np.abs(pts[:, 0]) > W / 2 + 3e-4) & (np.abs(pts[:, 0]) < W / 2 + 0.02))

    d, _, pts = _side_edge_sweep(far_dark, EmulationConfig.ideal(quantise=False))
    assert (d > 0).sum() > 20000 and not beyond(d, pts).any()
    ideal = EmulationConfig.ideal(quantise=False, divergence=True)
    d, inten, pts = _side_edge_sweep(far_dark, ideal)
    out = beyond(d, pts)
    assert out.sum() > 50  # both edges, six rings
    # at most the side sub-ray's 1 mrad beyond the edge (2.5-2.8 m away, the left edge seen
    # 25 deg off its normal), on the plane, 100 x 0.55 x 0.15 x cos(incidence) at most
    assert np.max(np.abs(pts[out, 0]) - W / 2) < 3.5e-3
    assert np.max(np.abs(pts[out, 1])) < 2e-3
    assert np.max(inten[out]) <= 9
    # the bench's own wall: the same beams report the wall's echo, 1.5 m farther
    d_bench, _, _ = _side_edge_sweep(BenchParams(), ideal)
    assert np.all(d_bench[out] > d[out] + 1.0)
    # with the twin's noise: the board's echo, with the 14 mm noise
    dev = []
    for seed in range(4):
        d_n, _, _ = _side_edge_sweep(far_dark, EmulationConfig(laser_offset_sigma=0.0), seed)
        ok = (d_n[out] > 0) & (np.abs(d_n[out] - d[out]) < 0.1)
        assert ok.mean() > 0.95
        dev.append(d_n[out][ok] - d[out][ok])
    dev = np.concatenate(dev)
    assert 0.012 < np.std(dev) < 0.016, np.std(dev)
    assert np.mean(np.abs(dev) < 5e-4) < 0.1  # N(0, 14 mm) puts 3 % there


def test_strongest_and_last_differ_only_at_edges() -> None:
    base = EmulationConfig.ideal(divergence=True)
    s = BenchSim(seed=0, noise=base.with_(return_mode="strongest")).scan()
    la = BenchSim(seed=0, noise=base.with_(return_mode="last")).scan()
    assert len(s) == len(la)
    diff = np.abs(s.distance - la.distance) > 0.01
    assert 0 < diff.sum() < 0.1 * len(s)
    assert np.all(la.distance[diff] >= s.distance[diff])
    # At the board's edges the last return is the wall behind it.
    pose = s.meta["truth_pose"]
    p_s = pose.transform(s.xyz)
    at_board_edge = diff & (np.abs(p_s[:, 1]) < 0.01) & (np.abs(p_s[:, 2]) < H / 2 + 0.01)
    assert at_board_edge.sum() >= 2
    p_l = pose.transform(la.xyz)[at_board_edge]
    assert np.all(p_l[:, 1] > 1.0)


def test_no_ray_sees_the_sensor_housing() -> None:
    sim = BenchSim(seed=0, noise=EmulationConfig.ideal())
    scan = sim.scan()
    assert scan.distance[scan.valid].min() > 0.5


def test_emulator_is_seeded() -> None:
    a = BenchSim(seed=42).scans(2)
    b = BenchSim(seed=42).scans(2)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.distance, y.distance)
        np.testing.assert_array_equal(x.intensity, y.intensity)
    c = BenchSim(seed=43).scan()
    assert not np.array_equal(a[0].distance[: len(c)], c.distance[: len(a[0])])


def test_ideal_turns_every_error_source_off() -> None:
    cfg = EmulationConfig.ideal()
    assert cfg.range_noise_sigma == 0 and cfg.laser_offset_sigma == 0 and cfg.range_bias == 0
    assert not cfg.divergence and not cfg.dropouts and not cfg.intensity_model
    assert cfg.rpm_wander_sigma == 0
    emu = BenchSim(seed=0, noise=cfg).emulator
    assert isinstance(emu, VLP16Emulator)
    np.testing.assert_array_equal(emu.laser_offsets, 0)
    with pytest.raises(ValueError):
        EmulationConfig(rpm=1500)


def _lab_and_bench_grid(scene: str, cfg: EmulationConfig, seed: int = 3):
    sim = BenchSim(BenchParams.from_edge(roll_deg=1.0, tilt_deg=-2.0, yaw_deg=1.5, scene=scene),
                   seed=seed, noise=cfg)
    sim.set_stage_positions(x_m=0.03, yaw_rad=math.radians(-7))
    p, r = sim.physics.lidar_pose_world()
    return sim.emulator.fire_grid(_grid(1800), p, r)


@pytest.mark.parametrize("mode", ["strongest", "dual"])
def test_adaptive_subrays_equal_the_brute_force_model_on_the_bench(mode: str) -> None:
    """On the bench every face is a box or a plane: the adaptive sub-rays (the centre first,
    MuJoCo only where the footprint may leave its face) give the brute-force model's returns
    exactly, noise included (the same draws in the same order)."""
    cfg = EmulationConfig(return_mode=mode)
    brute = _lab_and_bench_grid("bench", cfg.with_(subrays="all"))
    fast = _lab_and_bench_grid("bench", cfg)
    np.testing.assert_array_equal(fast.distance, brute.distance)
    np.testing.assert_array_equal(fast.intensity, brute.intensity)
    np.testing.assert_array_equal(fast.return_type, brute.return_type)
    np.testing.assert_array_equal(fast.x, brute.x)


def test_adaptive_subrays_keep_the_returns_distribution_in_the_lab() -> None:
    """In the cluttered lab (curved geoms, meshes, thin shelves in front of others) the
    adaptive sub-rays can miss an occluder no neighbouring beam meets: compared with the
    brute-force model, ray for ray without noise almost every firing is the same, and with
    every effect on the returns' distribution is (counts, second echoes, ranges per laser)."""
    ideal = EmulationConfig.ideal(quantise=False, divergence=True, return_mode="dual")
    brute = _lab_and_bench_grid("lab", ideal.with_(subrays="all"))
    fast = _lab_and_bench_grid("lab", ideal)
    differ = (np.abs(fast.distance - brute.distance) > 1e-6).any(axis=0)
    assert differ.mean() < 1e-3
    assert (brute.distance > 0).mean() > 0.85  # a closed room: almost every beam returns
    cfg = EmulationConfig(return_mode="dual")
    brute = _lab_and_bench_grid("lab", cfg.with_(subrays="all"), seed=5)
    fast = _lab_and_bench_grid("lab", cfg, seed=5)
    valid_f, valid_b = fast.distance > 0, brute.distance > 0
    assert abs(int(valid_f.sum()) - int(valid_b.sum())) < 1e-3 * valid_b.size
    two_f = (np.abs(fast.distance[0] - fast.distance[1]) > 0.5) & valid_f.all(axis=0)
    two_b = (np.abs(brute.distance[0] - brute.distance[1]) > 0.5) & valid_b.all(axis=0)
    assert abs(int(two_f.sum()) - int(two_b.sum())) <= max(5, 0.05 * two_b.sum())
    lid = np.tile(np.arange(16), 1800)
    for lsr in range(16):
        m = valid_f[0] & valid_b[0] & (lid == lsr)
        # The same beams, the same ranges but for the noise (14 mm over ~1800 firings).
        assert abs(np.mean(fast.distance[0, m] - brute.distance[0, m])) < 2e-3


def test_the_kernels_answer_the_lab_as_mujoco_does() -> None:
    """In the lab (73 boxes, curved geoms, meshes, six planes) the culled cast (boxes and
    planes by MuJoCo's own rules in the kernel, the rest against the curved geoms alone)
    returns what brute-force mj_multiRay over every geom returns (to rounding: the planes'
    rays are not cast along bit-identical directions on the two paths, as on the bench)."""
    params = BenchParams.from_edge(roll_deg=0.5, tilt_deg=1.0, scene="lab")
    cfg = EmulationConfig.ideal(quantise=False)
    sims = [BenchSim(params, seed=4, noise=cfg.with_(culling=c)) for c in (True, False)]
    for sim in sims:
        sim.set_stage_positions(x_m=-0.02, yaw_rad=math.radians(12))
    az = _grid(1800, phase=2.0)
    p, r = sims[0].physics.lidar_pose_world()
    fast = sims[0].emulator.fire_grid(az, p, r)
    brute = sims[1].emulator.fire_grid(az, p, r)
    np.testing.assert_allclose(fast.distance, brute.distance, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(fast.intensity, brute.intensity)
    assert (brute.distance > 0).mean() > 0.85


def test_the_kernels_give_mujocos_bits_in_the_lab() -> None:
    """`raykernel.solid_cast` (MuJoCo's own ray functions: boxes, planes, the person's
    capsules, the stool's cylinders, the castors' spheres, the meshes) equals mj_multiRay over
    every geom along the very same directions, bit for bit: distances, geoms and normals (so
    scans stay byte-identical), with no ray left to MuJoCo."""
    sim = BenchSim(BenchParams(scene="lab"), seed=0, noise=EmulationConfig.ideal())
    em, caster = sim.emulator, sim.caster
    az = _grid(1800, phase=0.7)
    p, r = sim.physics.lidar_pose_world()
    em.fire_grid(az, p, r)  # (its planes' rows for this grid, which the kernel uses too)
    _, _, row_laser, row_dh, cw, sw = em._grid_rows()
    base, d_first, spread = raykernel.grid_prepare(az, row_laser, row_dh)
    origins = p + np.outer(em._vertical_offsets, r[:, 2])
    idx, dirs, rows, bounds = em._grid_candidates(base, d_first, spread, az, row_laser, row_dh,
                                                  cw, sw, origins, r)
    assert len(idx) > 0.25 * az.size  # the lab: many rays are near some solid
    d, g, nv, flags, _ = em._cast_candidates(idx, dirs, rows, bounds, origins, row_laser,
                                             base, d_first, spread)
    assert not np.any(flags & raykernel.FLAG_MUJOCO)  # the kernels answer every ray
    d_b, g_b, n_b = caster.multiray_rows(origins[row_laser[rows]], bounds, dirs)
    np.testing.assert_array_equal(g, g_b)
    np.testing.assert_array_equal(d, d_b)
    np.testing.assert_array_equal(nv[g >= 0], n_b[g_b >= 0])
    # every kind of the lab's solids is met, so each kernel was held to MuJoCo here
    kinds = set(caster.kinds[np.unique(g[g >= 0])].tolist())
    assert {raykernel.KIND_BOX, raykernel.KIND_CAPSULE, raykernel.KIND_CYLINDER,
            raykernel.KIND_MESH} <= kinds


def test_without_firing_delays_every_laser_is_cast_at_its_sequences_azimuth() -> None:
    """`EmulationConfig.firing_delays` False: a world whose lasers of one sequence all fire at
    its first firing's azimuth, reported as a decoder that applies the VLP-16's 2.304 us
    delays reads it (the same azimuths as with the delays, the points at them)."""
    params = BenchParams.from_edge(roll_deg=2.0, tilt_deg=1.0, yaw_deg=-2.0)
    scans = {}
    for delays in (True, False):
        sim = BenchSim(params, seed=1, noise=EmulationConfig.ideal(quantise=False,
                                                                   firing_delays=delays))
        sim.move_to(x_m=0.01, yaw_rad=math.radians(5.0))
        scans[delays] = sim.scan()
    ref, off = scans[True], scans[False]
    np.testing.assert_array_equal(off.azimuth, ref.azimuth)
    np.testing.assert_array_equal(off.laser_id, ref.laser_id)
    pose = off.meta["truth_pose"]
    omega = off.meta["rpm"] * 2 * math.pi / 60
    cast = off.azimuth - off.laser_id * vlp16.LASER_PERIOD * omega
    rng_c, on = board_intersections(pose, cast, off.laser_id, W - 0.01, H - 0.01)
    assert on.sum() > 400
    np.testing.assert_allclose(off.distance[on], rng_c[on], atol=1e-6)
    # The reported azimuths are not where the rays went: the ranges differ from the delays'.
    assert np.max(np.abs(off.distance[on] - ref.distance[on])) > 1e-4
    # The points are at the reported azimuths (as a decoder puts them).
    v = off.valid
    np.testing.assert_allclose(np.mod(np.arctan2(off.x[v], off.y[v]), 2 * math.pi),
                               off.azimuth[v], atol=1e-9)

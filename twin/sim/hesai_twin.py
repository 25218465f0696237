"""A Hesai PandarXT32 or PandarQT128 on the twin's bench, written as its own data packets.

Every firing is a MuJoCo ray (`twin.sim.emulation.RayCaster.cast`) from the optical centre at
the azimuth the head has when that channel fires: its block's azimuth, plus the rotation until
the channel fires (omega from the rpm, times the channel's firetime in its loop: Hesai's
firetime correction files, `twin.lidar.hesai.HesaiModel.firetime`; the head turns the way the
azimuth increases), plus the channel's azimuth offset; at the channel's elevation (the unit's
angle-correction file). The packet carries the block's azimuth, as a real unit's does, so a
decoder that leaves the rotation out (nebula's, ``decode_hesai(..., firetime=False)``) reads
each channel up to 0.19 deg (XT32) or 0.36 deg (QT128) short of where it looked, at 600 rpm;
aimbench's default decode puts it back. The bench stands still meanwhile.

PandarXT32: blocks 50 us apart (0.18 deg at 600 rpm, 2,000 a turn), 8 a packet, single return
(strongest). PandarQT128C2X: firings 111.11 us apart (0.4 deg at 600 rpm, 900 a
turn), one a packet, in the real unit's default dual-return mode (0x39, last and strongest: a
single echo written in both blocks, as the real capture's flat surfaces are), its two firing
loops alternating packet by packet with the dark channels of each loop not fired (distance 0),
the three CRCs and 32 zero bytes of cyber security: 1127 bytes as the real unit sends; or in
a single-return mode (``return_mode``), two firings a packet, block 0 loop 1 and block 1 loop 2.
Measurement model (assumed, stated): Gaussian range noise of 1 sigma ``range_sigma`` (default
10 mm, the order of both datasheets' +-1 cm accuracy), the packet's 4 mm unit, no return
nearer than 0.05 m or beyond nebula's limit for the model (120 m XT32, 50 m QT128), a sharp
beam, reflectivity 100 x the surface's diffuse reflectance x the cosine of incidence.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from twin.core.pose import Pose
from twin.lidar.hesai import (
    DATA_PORT,
    N_CHANNELS,
    QT128,
    QT128_FIRED,
    QT128_SINGLE_MODES,
    XT32,
    HesaiAngles,
    encode_qt128,
    encode_xt32,
)
from twin.lidar.pcap import PcapWriter

BLOCK_PERIOD = 50e-6  # s
BLOCKS_PER_PACKET = 8


def _cast(sim, angles: HesaiAngles, block_cdeg: np.ndarray, fired: np.ndarray,
          firetime: np.ndarray, rpm: float, rng: np.random.Generator, range_sigma: float,
          max_range: float) -> tuple[np.ndarray, np.ndarray]:
    """Distances (m, 0: none) and reflectivities of the fired channels of each firing at
    ``block_cdeg`` (n,), ``fired`` (n, channels): one ray each from the optical centre, at the
    azimuth the head turning at ``rpm`` has ``firetime`` (n, channels; s) after the block's."""
    omega = rpm * 2.0 * np.pi / 60.0  # rad/s, the direction the azimuth increases
    a = (np.radians(block_cdeg / 100.0)[:, None] + omega * firetime
         + np.radians(angles.azimuth_deg))
    el = np.broadcast_to(np.radians(angles.elevation_deg)[None, :], a.shape)
    a, el = a[fired], el[fired]
    d_l = np.column_stack((np.cos(el) * np.sin(a), np.cos(el) * np.cos(a), np.sin(el)))
    p_w, r_w = sim.physics.lidar_pose_world()
    d_w = d_l @ r_w.T
    t, gid, nrm = sim.caster.cast(np.broadcast_to(p_w, d_w.shape).copy(), d_w)
    refl_of = sim.params.geom_reflectivity(sim.physics.model)
    r = t + rng.normal(0.0, range_sigma, t.shape)
    hit = np.isfinite(t) & (gid >= 0) & (r > 0.05) & (r < max_range)
    cos_inc = np.abs(np.einsum("ij,ij->i", nrm, d_w))
    dist = np.zeros(fired.shape)
    refl = np.zeros(fired.shape, dtype=np.uint8)
    dist[fired] = np.where(hit, np.where(hit, r, 0.0), 0.0)
    refl[fired] = np.where(hit, np.minimum(255, np.rint(100.0 * refl_of[np.maximum(gid, 0)]
                                                        * cos_inc)), 0)
    return dist, refl


def emulate_xt32(sim, angles: HesaiAngles, n_rotations: int, *, rng: np.random.Generator,
                 rpm: float = 600.0, range_sigma: float = 0.01,
                 start_cdeg: int = 0) -> tuple[list[bytes], Pose]:
    """Packets of ``n_rotations`` turns of ``sim``'s bench (a `twin.sim.bench.BenchSim` at
    rest) as a PandarXT32 sees it, from ``start_cdeg``; and the true pose of {L} in {O}."""
    per_turn = round(60.0 / rpm / BLOCK_PERIOD)
    n_packets = -(-(n_rotations * per_turn + 1) // BLOCKS_PER_PACKET)
    k = np.arange(n_packets * BLOCKS_PER_PACKET)
    block_cdeg = np.rint(start_cdeg + k * (36000.0 / per_turn)).astype(np.int64) % 36000
    fired = np.ones((len(k), N_CHANNELS), dtype=bool)
    dist, refl = _cast(sim, angles, block_cdeg, fired,
                       np.broadcast_to(XT32.firetime[0], fired.shape), rpm, rng, range_sigma,
                       XT32.max_range)
    ts = np.rint(np.arange(n_packets) * BLOCKS_PER_PACKET * BLOCK_PERIOD * 1e6).astype(np.int64)
    packets = encode_xt32(block_cdeg.reshape(-1, BLOCKS_PER_PACKET),
                          dist.reshape(-1, BLOCKS_PER_PACKET, N_CHANNELS),
                          refl.reshape(-1, BLOCKS_PER_PACKET, N_CHANNELS), ts, rpm=rpm)
    return packets, sim.physics.lidar_pose_in_board()


def emulate_qt128(sim, angles: HesaiAngles, n_rotations: int, *, rng: np.random.Generator,
                  rpm: float = 600.0, range_sigma: float = 0.01, start_cdeg: int = 0,
                  return_mode: int = 0x39) -> tuple[list[bytes], Pose]:
    """Packets of ``n_rotations`` turns of ``sim``'s bench as a PandarQT128C2X sees it from
    ``start_cdeg``, and the true pose of {L} in {O}. ``return_mode``: 0x39 (dual, the real
    unit's default) one firing a packet, its echo in both blocks; a single-return byte
    (`twin.lidar.hesai.QT128_SINGLE_MODES`, e.g. 0x37) two firings a packet, block 0 loop 1
    and block 1 loop 2 (nebula's pandar_qt128.hpp), the packet stamped at its first block."""
    period = QT128.firing_period
    per_turn = round(60.0 / rpm / period)
    single = return_mode in QT128_SINGLE_MODES
    n = n_rotations * per_turn + 1
    k = np.arange(n + (n % 2 if single else 0))  # single: whole packets of two firings
    block_cdeg = np.rint(start_cdeg + k * (36000.0 / per_turn)).astype(np.int64) % 36000
    loop = k % 2  # loop 1 and loop 2 alternate firing by firing
    dist, refl = _cast(sim, angles, block_cdeg, QT128_FIRED[loop], QT128.firetime[loop], rpm,
                       rng, range_sigma, QT128.max_range)
    if single:  # firings 2j (loop 1) and 2j + 1 (loop 2) are packet j's blocks 0 and 1
        ts = np.rint(k[::2] * period * 1e6).astype(np.int64)
        packets = encode_qt128(block_cdeg.reshape(-1, 2), dist.reshape(-1, 2, QT128.n_channels),
                               refl.reshape(-1, 2, QT128.n_channels), ts, loop[::2], rpm=rpm,
                               return_mode=return_mode)
        return packets, sim.physics.lidar_pose_in_board()
    ts = np.rint(k * period * 1e6).astype(np.int64)
    packets = encode_qt128(np.column_stack((block_cdeg, block_cdeg)),
                           np.stack((dist, dist), axis=1), np.stack((refl, refl), axis=1), ts,
                           loop, rpm=rpm)
    return packets, sim.physics.lidar_pose_in_board()


#: The twin of each Hesai model, and the s between its packets (the firing's period is the
#: sensor's clock: another rpm changes the firings a turn, as on the XT32).
EMULATORS = {XT32.name: (emulate_xt32, BLOCKS_PER_PACKET * BLOCK_PERIOD),
             QT128.name: (emulate_qt128, QT128.firing_period)}


def emulate_hesai(sim, angles: HesaiAngles, n_rotations: int, **kwargs) -> tuple[list[bytes],
                                                                                  Pose]:
    """`emulate_xt32` or `emulate_qt128`, by the model of ``angles``."""
    return EMULATORS[angles.model.name][0](sim, angles, n_rotations, **kwargs)


def write_hesai_pcap(sim, angles: HesaiAngles, path: str | Path, n_rotations: int, *,
                     rng: np.random.Generator, epoch_s: float = 1.7e9, **kwargs) -> Pose:
    """The packets of `emulate_hesai` in a pcap (UDP port 2368); the true pose."""
    packets, truth = emulate_hesai(sim, angles, n_rotations, rng=rng, **kwargs)
    dt = EMULATORS[angles.model.name][1]
    if kwargs.get("return_mode") in QT128_SINGLE_MODES and angles.model.name == QT128.name:
        dt *= 2  # a single-return QT128 packet holds two firings, one of each loop
    with PcapWriter(path) as out:
        for i, p in enumerate(packets):
            out.write_udp(p, epoch_s + i * dt, dst_port=DATA_PORT, src_port=10000)
    return truth


def write_xt32_pcap(sim, angles: HesaiAngles, path: str | Path, n_rotations: int, *,
                    rng: np.random.Generator, epoch_s: float = 1.7e9, **kwargs) -> Pose:
    """The packets of `emulate_xt32` in a pcap (UDP port 2368); the true pose."""
    return write_hesai_pcap(sim, angles, path, n_rotations, rng=rng, epoch_s=epoch_s, **kwargs)

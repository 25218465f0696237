"""A Hesai PandarXT32 on the twin's bench, written as its own data packets.

Every firing is a MuJoCo ray (`twin.sim.emulation.RayCaster.cast`) from the optical centre at
its block's azimuth plus the channel's azimuth offset and the channel's elevation (the unit's
angle-correction file, `twin.lidar.hesai`): what the decoder reads back. The blocks are 50 us
apart (0.18 deg at 600 rpm, 2,000 a turn), 8 a packet; the bench stands still meanwhile.
Measurement model (assumed, stated): Gaussian range noise of 1 sigma ``range_sigma`` (default
10 mm, the order of the datasheet's +-1 cm accuracy), the packet's 4 mm unit, no return nearer
than 0.05 m or beyond 120 m (nebula's limits for the XT32), a sharp beam, reflectivity 100 x
the surface's diffuse reflectance x the cosine of incidence. Single return (strongest).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from twin.core.pose import Pose
from twin.lidar.hesai import DATA_PORT, N_CHANNELS, XT32Angles, encode_xt32
from twin.lidar.pcap import PcapWriter

BLOCK_PERIOD = 50e-6  # s
BLOCKS_PER_PACKET = 8


def emulate_xt32(sim, angles: XT32Angles, n_rotations: int, *, rng: np.random.Generator,
                 rpm: float = 600.0, range_sigma: float = 0.01,
                 start_cdeg: int = 0) -> tuple[list[bytes], Pose]:
    """Packets of ``n_rotations`` turns of ``sim``'s bench (a `twin.sim.bench.BenchSim` at
    rest) as a PandarXT32 sees it, from ``start_cdeg``; and the true pose of {L} in {O}."""
    per_turn = round(60.0 / rpm / BLOCK_PERIOD)
    n_packets = -(-(n_rotations * per_turn + 1) // BLOCKS_PER_PACKET)
    k = np.arange(n_packets * BLOCKS_PER_PACKET)
    block_cdeg = np.rint(start_cdeg + k * (36000.0 / per_turn)).astype(np.int64) % 36000
    a = np.radians(block_cdeg / 100.0)[:, None] + np.radians(angles.azimuth_deg)
    el = np.radians(angles.elevation_deg)[None, :]
    d_l = np.stack(np.broadcast_arrays(np.cos(el) * np.sin(a), np.cos(el) * np.cos(a),
                                       np.sin(el)), axis=-1).reshape(-1, 3)
    p_w, r_w = sim.physics.lidar_pose_world()
    d_w = d_l @ r_w.T
    t, gid, nrm = sim.caster.cast(np.broadcast_to(p_w, d_w.shape).copy(), d_w)
    refl_of = sim.params.geom_reflectivity(sim.physics.model)
    r = t + rng.normal(0.0, range_sigma, t.shape)
    hit = np.isfinite(t) & (gid >= 0) & (r > 0.05) & (r < 120.0)
    dist = np.where(hit, np.where(hit, r, 0.0), 0.0).reshape(-1, BLOCKS_PER_PACKET, N_CHANNELS)
    cos_inc = np.abs(np.einsum("ij,ij->i", nrm, d_w))
    refl = np.where(hit, np.minimum(255, np.rint(100.0 * refl_of[np.maximum(gid, 0)] * cos_inc)),
                    0).astype(np.uint8).reshape(dist.shape)
    ts = np.rint(np.arange(n_packets) * BLOCKS_PER_PACKET * BLOCK_PERIOD * 1e6).astype(np.int64)
    packets = encode_xt32(block_cdeg.reshape(-1, BLOCKS_PER_PACKET), dist, refl, ts, rpm=rpm)
    return packets, sim.physics.lidar_pose_in_board()


def write_xt32_pcap(sim, angles: XT32Angles, path: str | Path, n_rotations: int, *,
                    rng: np.random.Generator, epoch_s: float = 1.7e9, **kwargs) -> Pose:
    """The packets of `emulate_xt32` in a pcap (UDP port 2368); the true pose."""
    packets, truth = emulate_xt32(sim, angles, n_rotations, rng=rng, **kwargs)
    with PcapWriter(path) as out:
        for i, p in enumerate(packets):
            out.write_udp(p, epoch_s + i * BLOCKS_PER_PACKET * BLOCK_PERIOD,
                          dst_port=DATA_PORT, src_port=10000)
    return truth

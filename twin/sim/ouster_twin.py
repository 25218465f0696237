"""An Ouster OS0 / OS1 / OS2 on the twin's bench, emulated from its metadata, written as the
sensor's own packets (LEGACY, or another profile: `frame_packets`) in a pcap with the metadata
JSON beside it, or as an OSF file through ouster-sdk's writer (`twin.lidar.ouster_sdk`), the
metadata in it.

Every pixel of a frame is a MuJoCo ray (`twin.sim.emulation.RayCaster.cast`, the cast the
Velodyne emulation makes) from its beam's origin, in its beam's direction, both as ouster-sdk's
xyzlut.cpp puts them (`twin.lidar.ouster`): column c fires at encoder angle 2 pi (1 - c / W),
beam b at its altitude and its azimuth offset, from lidar_origin_to_beam_origin_mm off the
axis along the encoder's direction. The range reported is the beam origin's distance plus that
offset, in mm, as the sensor reports it, so decoding the packets puts each point where the ray
met the scene. The columns of a frame fire 1 / (W x rate) apart; the bench stands still while
a frame is taken (the stages are at rest between moves).

Measurement model (each an assumption, stated): Gaussian range noise, 1 sigma
``range_sigma`` (default 10 mm, of the order of the OS1 datasheet's precision at a few metres);
1 mm quantisation (the packet's unit); no return nearer than 0.3 m or beyond 120 m; a sharp beam
(no divergence, no mixed returns); reflectivity 100 x the surface's diffuse reflectance x the
cosine of incidence, capped at 255; signal as reflectivity, near-IR 0.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from twin.core.pose import Pose
from twin.lidar.ouster import (
    COLUMN_VALID,
    Frame,
    OusterInfo,
    columns_from_frame,
    encode_frame,
    encode_packets,
    info_json,
)
from twin.lidar.pcap import PcapWriter

#: The serial number the twin's non-LEGACY packet headers carry (its metadata's prod_sn is
#: "twin", which no packet header's 40-bit number can say).
TWIN_SERIAL = 0
RANGE_MIN = 0.3  # m
RANGE_MAX = 120.0  # m


def beam_rays(info: OusterInfo) -> tuple[np.ndarray, np.ndarray]:
    """Origins (m) and unit directions of every pixel in {L}, each (H, W, 3)."""
    h, w = info.pixels_per_column, info.columns_per_frame
    enc = 2.0 * np.pi - np.arange(w) * (2.0 * np.pi / w)
    az = -np.radians(info.beam_azimuth_deg)[:, None]
    alt = np.radians(info.beam_altitude_deg)[:, None]
    d = np.stack(np.broadcast_arrays(np.cos(enc + az) * np.cos(alt),
                                     np.sin(enc + az) * np.cos(alt),
                                     np.broadcast_to(np.sin(alt), (h, w))), axis=-1)
    bx, bz = info.beam_to_lidar_mm
    o = np.stack(np.broadcast_arrays(np.cos(enc)[None, :] * bx, np.sin(enc)[None, :] * bx,
                                     np.full((h, w), bz)), axis=-1) * 1e-3
    rot = info.lidar_to_sensor[:3, :3]
    d, o = d @ rot.T, o @ rot.T
    # {L}: X_L = -y, Y_L = x of the sensor frame's axes
    to_l = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    return o @ to_l.T, d @ to_l.T


def emulate_frames(sim, info: OusterInfo, n_frames: int, *, rng: np.random.Generator,
                   range_sigma: float = 0.01, t0_s: float = 0.0,
                   first_frame_id: int = 0) -> tuple[list[Frame], Pose]:
    """``n_frames`` frames of ``sim``'s bench (a `twin.sim.bench.BenchSim`, at rest) as the
    Ouster of ``info`` sees it, and the true pose of {L} in the board frame."""
    h, w = info.pixels_per_column, info.columns_per_frame
    origins, dirs = beam_rays(info)
    p_w, r_w = sim.physics.lidar_pose_world()
    o_world = (origins.reshape(-1, 3) @ r_w.T) + p_w
    d_world = dirs.reshape(-1, 3) @ r_w.T
    refl_of = sim.params.geom_reflectivity(sim.physics.model)
    n_mm = float(np.hypot(*info.beam_to_lidar_mm))
    t, gid, nrm = sim.caster.cast(o_world, d_world)
    t, gid = t.reshape(h, w), gid.reshape(h, w)
    cos_inc = np.abs(np.einsum("ij,ij->i", nrm, d_world)).reshape(h, w)
    period_ns = 1e9 / (w * info.rate_hz)
    frames = []
    for k in range(n_frames):
        r = t + rng.normal(0.0, range_sigma, t.shape)
        hit = np.isfinite(t) & (gid >= 0) & (r > RANGE_MIN) & (r < RANGE_MAX)
        range_mm = np.where(hit, np.rint(np.where(hit, r, 0.0) * 1e3 + n_mm), 0).astype(np.uint32)
        refl = np.where(hit, np.minimum(255, np.rint(100.0 * refl_of[np.maximum(gid, 0)]
                                                     * cos_inc)), 0).astype(np.uint8)
        t_frame = t0_s * 1e9 + k * w * period_ns
        frames.append(Frame(
            frame_id=(first_frame_id + k) % 65536, range_mm=range_mm, reflectivity=refl,
            signal=refl.astype(np.uint16), near_ir=np.zeros((h, w), dtype=np.uint16),
            timestamp_ns=(t_frame + np.arange(w) * period_ns).astype(np.uint64),
            measurement_id=np.arange(w, dtype=np.uint16),
            status=np.full(w, COLUMN_VALID, dtype=np.uint32), received=np.ones(w, dtype=bool),
            packets=w // info.columns_per_packet))
    return frames, sim.physics.lidar_pose_in_board()


def write_ouster_pcap(sim, info: OusterInfo, path: str | Path, n_frames: int, *,
                      rng: np.random.Generator, range_sigma: float = 0.01,
                      epoch_s: float = 1.7e9) -> Pose:
    """Write ``n_frames`` frames as packets of ``info``'s profile (`frame_packets`) to a pcap
    (UDP port ``info``'s, 7502) and the metadata to ``NAME.json`` beside it; the true pose of
    {L} in the board frame."""
    path = Path(path)
    frames, truth = emulate_frames(sim, info, n_frames, rng=rng, range_sigma=range_sigma)
    packet_s = info.columns_per_packet / (info.columns_per_frame * info.rate_hz)
    with PcapWriter(path) as out:
        i = 0
        for f in frames:
            for payload in frame_packets(f, info):
                out.write_udp(payload, epoch_s + i * packet_s, dst_port=info.udp_port_lidar,
                              src_port=info.udp_port_lidar)
                i += 1
    path.with_suffix(".json").write_text(info_json(info))
    return truth


def frame_packets(frame: Frame, info: OusterInfo) -> list[bytes]:
    """A frame's packets in the metadata's profile (LEGACY's as before; the others with the
    twin's serial number and init id 0, as its metadata, which states neither, is read)."""
    if info.udp_profile_lidar == "LEGACY":
        return encode_packets(columns_from_frame(frame, info), info)
    return encode_frame(frame, info, init_id=0, prod_sn=TWIN_SERIAL)


def write_ouster_osf(sim, info: OusterInfo, path: str | Path, n_frames: int, *,
                     rng: np.random.Generator, range_sigma: float = 0.01) -> Pose:
    """Write ``n_frames`` frames to an OSF file through ouster-sdk's writer (Ouster's own tools
    read it; the metadata in it); the true pose of {L} in the board frame. The frames are those
    `write_ouster_pcap` writes for the same ``rng``."""
    from twin.lidar.ouster_sdk import write_osf  # ouster-sdk, loaded only for an OSF

    frames, truth = emulate_frames(sim, info, n_frames, rng=rng, range_sigma=range_sigma)
    write_osf(path, frames, info)
    return truth

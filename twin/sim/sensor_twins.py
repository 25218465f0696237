"""Scans of any sensor aimbench emulates, at one pose of the bench: the one call a comparison of
sensors makes (a study over ``sensor.model``, `benchmarks/bench_models.py`).

The Velodyne models are `twin.sim.bench.BenchSim`'s own emulation (its `EmulationConfig.model`).
An Ouster (OS0/OS1/OS2, 32/64/128 beams, 1024x10) and a Hesai PandarXT32 or PandarQT128 have
twins of their own (`twin.sim.ouster_twin`, `twin.sim.hesai_twin`) that cast the bench's rays
from their beams and write the sensor's packets; their scans here are those packets decoded by
aimbench's decoders (`twin.lidar.ouster`, `twin.lidar.hesai`), as a capture of the real sensor
would be. `firing_of` gives the firing pattern the precision bound (`align.design.bound.Firing`)
needs. SI units.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from twin.core.pose import Pose
from twin.core.scan import Scan
from twin.lidar.hesai import HESAI_MODELS as HESAI_DECODED
from twin.lidar.ouster import is_ouster_model, ouster_model_name

#: The Hesai models the twin emulates: every one the decoder reads (their angle files:
#: `twin.lidar.hesai.default_angles`).
HESAI_MODELS = tuple(HESAI_DECODED)


def is_own_twin(model: str) -> bool:
    """Whether ``model`` has a twin of its own (an Ouster, a Hesai: the models with a decoder of
    their own, `twin.lidar.sources.own_decoder`) rather than `BenchSim`'s."""
    from twin.lidar.sources import own_decoder

    return own_decoder(model)


@dataclass(frozen=True)
class FiringPattern:
    """What the precision bound needs of a sensor's firing (`align.design.bound.Firing`): spin
    rate (rpm), s between two firings of one laser, each laser's time within that step (None:
    all at once, as an Ouster's column fires every beam together), and whether every scan fires
    at the same azimuths (``phase_locked``)."""

    rpm: float
    period: float
    laser_times: tuple[float, ...] | None
    phase_locked: bool


def firing_of(model: str) -> FiringPattern | None:
    """The firing of an Ouster or Hesai twin (None for a Velodyne model: `BenchSim`'s own)."""
    if is_ouster_model(model):
        from twin.lidar.ouster import nominal_info

        # An Ouster measures at fixed encoder positions (column c at 2 pi (1 - c / W)): every
        # frame samples the same azimuths, its twin's too.
        info = nominal_info(ouster_model_name(model))
        return FiringPattern(60.0 * info.rate_hz, 1.0 / (info.columns_per_frame * info.rate_hz),
                             None, True)
    if model == "PandarXT32":
        from twin.lidar.hesai import XT32
        from twin.sim.hesai_twin import BLOCK_PERIOD

        # The twin's PandarXT32 turns at exactly 600 rpm: its blocks repeat their azimuths every
        # turn, as a unit phase-locked to its clock does (a free-running one's wander). Each
        # channel fires its firetime after the block's azimuth (6 + 1.512 n us: the twin casts
        # it there, `twin.sim.hesai_twin`), so the channels' phases within the 0.18 deg step
        # spread over 0.17 deg (a vernier) instead of being unknown.
        return FiringPattern(600.0, BLOCK_PERIOD, tuple(float(t) for t in XT32.firetime[0]),
                             True)
    if model == "PandarQT128":
        from twin.lidar.hesai import QT128

        # Phase-locked as the XT32's. The lasers that see a board near the horizon (channels
        # 33-64, -18 to +6 deg) fire in one of the two loops only: every other firing, 0.8 deg
        # at 600 rpm (channels 65-128 every firing, 0.4 deg: the bound is pessimistic for
        # them). The twin casts each channel at its block's azimuth plus the rotation until it
        # fires (its loop's firetime): loop 1 at the period's start, loop 2 (channels 1-32)
        # half a period later, each plus its firetime in that loop (channels 65-128: loop 1's,
        # the one phase the bound takes). Their times matter: channels 33-64 share one azimuth
        # offset within 0.3 deg, so their brackets along a side edge fall at phases the
        # firetimes set, and the bound with the phases unknown (averaged) said half the
        # twin's roll spread (0.31 against 0.62 deg fused, benchmarks/bench_models.py, before
        # the firetimes were in the twin).
        ft = QT128.firetime
        times = tuple(float(QT128.firing_period + ft[1, c] if c < 32 else ft[0, c])
                      for c in range(128))
        return FiringPattern(600.0, 2 * QT128.firing_period, times, True)
    return None


@dataclass(frozen=True)
class TwinPackets:
    """What an Ouster's or a Hesai's twin sent for some scans at rest: its datagrams, each
    one's time from the first (s) and UDP port, the scans aimbench's decoder reads from them
    (each carrying the twin's truth, ``meta["truth_pose"]``, as `BenchSim`'s scans do), the true
    pose of {L} in {O}, and the metadata JSON a capture keeps beside it (an Ouster's; None for
    a Hesai, whose angle file is the model's own)."""

    payloads: list[bytes]
    times_s: np.ndarray
    port: int
    scans: list[Scan]
    truth: Pose
    metadata_json: str | None


def own_twin_packets(sim: Any, model: str, n: int, *, rng: np.random.Generator,
                     range_sigma: float = 0.01, first_frame: int = 0,
                     t0_s: float = 0.0) -> TwinPackets:
    """``n`` scans of an Ouster's or a Hesai's twin on ``sim`` (a `twin.sim.bench.BenchSim`
    at rest, its stages where they are) through its packets and aimbench's decoder. Gaussian
    range noise of ``range_sigma`` (m) drawn from ``rng``. ``first_frame``, ``t0_s``: an
    Ouster's first frame id and its sensor time, s (a capture that goes on from earlier packets
    numbers its frames on)."""
    if is_ouster_model(model):
        from twin.lidar.ouster import (
            columns_from_frame,
            encode_packets,
            info_json,
            nominal_info,
            scans_from_payloads,
        )
        from twin.sim.ouster_twin import emulate_frames

        info = nominal_info(ouster_model_name(model))
        frames, truth = emulate_frames(sim, info, n, rng=rng, range_sigma=range_sigma,
                                       t0_s=t0_s, first_frame_id=first_frame)
        payloads = [p for f in frames for p in encode_packets(columns_from_frame(f, info), info)]
        packet_s = info.columns_per_packet / (info.columns_per_frame * info.rate_hz)
        return _with_truth(TwinPackets(
            payloads, np.arange(len(payloads)) * packet_s, info.udp_port_lidar,
            scans_from_payloads(payloads, info), truth, info_json(info)))
    if model in HESAI_MODELS:
        from twin.lidar.hesai import DATA_PORT, HesaiAngles, HesaiScans, default_angles
        from twin.sim.hesai_twin import EMULATORS, emulate_hesai

        angles = HesaiAngles.from_csv(default_angles(model), model)
        # one turn more than asked: the first packet starts mid-turn, a quarter turn in
        packets, truth = emulate_hesai(sim, angles, n + 1, rng=rng, range_sigma=range_sigma,
                                       start_cdeg=9000)
        return _with_truth(TwinPackets(
            packets, np.arange(len(packets)) * EMULATORS[angles.model.name][1], DATA_PORT,
            list(HesaiScans(packets, angles))[:n], truth, None))
    raise ValueError(f"{model!r} has no twin of its own: it is BenchSim's (EmulationConfig.model)")


def _with_truth(packets: TwinPackets) -> TwinPackets:
    for scan in packets.scans:
        scan.meta.update(truth=packets.truth.to_edge(), truth_pose=packets.truth)
    return packets


def own_twin_scans(params: Any, model: str, *, x: float, yaw: float, n: int, seed: int,
                   range_sigma: float = 0.01) -> tuple[list[Scan], Pose]:
    """``n`` scans of an Ouster's or a Hesai's twin on the bench of ``params`` (a
    `twin.sim.params.BenchParams`) with the stages at ``x`` (m) and ``yaw`` (rad), through its
    packets and aimbench's decoder; and the true pose of {L} in the board frame. Gaussian range
    noise of ``range_sigma`` (m); ``seed`` seeds the bench and the noise."""
    from twin.sim.bench import BenchSim

    sim = BenchSim(params, seed=seed)
    sim.move_to(x_m=x, yaw_rad=yaw)
    got = own_twin_packets(sim, model, n, rng=np.random.default_rng(seed),
                           range_sigma=range_sigma)
    return got.scans, got.truth


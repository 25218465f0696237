"""The inspection live in rerun (``aimbench inspect --rerun``): the board, the scan, the returns
and edge rays the estimate used, the nominal and the estimated LiDAR frame, each axis's
mounting error as a series, and the verdict in the log.

Built on the recording's own `log_*` functions (`scenarios.recording.log`): the world is the
board frame {O}; ``world/nominal`` is the LiDAR's nominal pose (static), ``world/estimate``
the estimated one, ``world/sensor`` draws the scan where the estimate puts it;
``plots/estimate/<axis>`` holds the mounting error (mm, deg) of each judgement. Sinks as for
a sweep (``--save``, ``--connect``, ``--serve``, ``--spawn``); without one, ``DB.rrd`` beside
the record store.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from scenarios.recording import log as rl
from scenarios.recording.observer import close_recording, open_recording, sink_options
from twin.core.pose import Pose
from twin.core.scan import Scan

_LEVEL = {"pass": "INFO", "fail": "ERROR", "inconclusive": "WARN"}


class LiveView:
    """One recording for a command's inspections (one unit, or a simulated line)."""

    def __init__(self, station: Any, sinks: Any) -> None:
        self.station = station
        self.sinks = sinks
        self.rec = open_recording("aimbench inspect", sinks, truth=False)
        self.step = 0
        rl.log_world(self.rec)
        board = station.board_spec()
        rl.log_board(self.rec, board.width, board.height)
        self._nominal_logged = False

    @classmethod
    def from_args(cls, args: Any, station: Any) -> LiveView:
        return cls(station, sink_options(args, default_save=Path(args.db).with_suffix(".rrd")))

    def _log_nominal(self, nominal: Pose) -> None:
        # {O} <- {W} <- {S} <- {L}: the nominal pose is given in the station frame.
        o_from_w = np.linalg.inv(self.station.board_in_bench())
        w_from_s = self.station.frame.pose.to_pose().matrix()
        m = o_from_w @ w_from_s @ nominal.matrix()
        rl.log_pose(self.rec, "world/nominal", Pose.from_matrix(m[:3, :3], m[:3, 3]), 0.3)
        self._nominal_logged = True

    def on_attempt(self, insp: Any) -> None:
        """After each judgement: the scans, what was used, the frames, the errors."""
        if not self._nominal_logged and insp.nominal is not None:
            self._log_nominal(insp.nominal)
        rl.set_scan_time(self.rec, self.step)
        self.step += 1
        est = insp.estimate
        pose = est.pose if est is not None and est.success else None
        rl.log_pose(self.rec, "world/estimate", pose)
        if insp.scans:
            scan = insp.scans[0] if len(insp.scans) == 1 else Scan.concatenate(insp.scans)
            if pose is not None:
                self.rec.log("world/sensor", rl.pose_transform(pose))
            rl.log_scan_points(self.rec, insp.scans[-1])
            rl.log_used(self.rec, scan, est.used if pose is not None else None)
        if insp.error is not None:
            rl.log_errors(self.rec, Pose.from_array(insp.error), None)
        rl.log_text(self.rec, f"unit {insp.unit}, {insp.scans_used} scans: "
                              f"{str(insp.verdict).upper()} ({insp.message})",
                    _LEVEL[str(insp.verdict)])

    def on_verdict(self, insp: Any, record: int) -> None:
        rl.log_text(self.rec, f"unit {insp.unit}: {str(insp.verdict).upper()} (record {record})",
                    _LEVEL[str(insp.verdict)])

    def close(self) -> None:
        close_recording(self.rec, self.sinks)

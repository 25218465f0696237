"""The inspection station: is a LiDAR just bolted onto a unit (a vehicle, a robot) mounted within
its specification? (issue 16; docs/inspection.md)

One board stands in front of the unit; `aimbench inspect` takes N scans, estimates the LiDAR's
pose (`align.estimate`), expresses it in the station frame as the mounting error from the
station file's nominal pose, with its covariance, judges each axis against the station's
tolerances with ISO 14253-1 guard bands, re-measures with more scans when that is inconclusive,
and keeps a record of every unit in a crash-safe SQLite file.

Modules, one concern each:

- `mounting`: the estimate (board frame) to the mounting error in the station frame, covariance
  carried through; the nominal pose.
- `verdict`: the decision rules (``iso14253-1``, ``simple``) per axis and for the unit.
- `acquire`: scans from a live sensor, a capture or the twin, keeping the raw capture.
- `procedure`: one unit's inspection: acquire, estimate, judge, re-measure.
- `records`: the per-unit record store (SQLite), its listing and exports.
- `report`: the one-page report of a unit and the line's summary (HTML and PNG).
- `line`: a simulated production line of twin units with random misalignments.
- `msa`: the measurement-system studies: gauge R&R (crossed ANOVA) and bias and linearity.
- `live`: the rerun view of an inspection.
"""

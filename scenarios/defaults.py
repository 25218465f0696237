"""The bench's procedures' defaults that the command line states, as plain numbers: the
calibration's, the inspection's, the simulated line's and a run's. The modules that run the
procedures (numpy, pydantic, the estimator) take them from here, so a command's parser states
them without importing those (issue 38: a command's parser within 0.5 s).
"""

#: Stage yaws the simulated calibration visits, deg: the sweep's range, so that every laser
#: that meets the board in a sweep is calibrated (a partial correction can do more harm)
#: (`scenarios.calibrate.DEFAULT_YAWS_DEG`).
CALIBRATION_YAWS_DEG = (-8.0, 0.0, 8.0)
#: Scans at each of those yaws (`scenarios.calibrate.DEFAULT_SCANS`).
CALIBRATION_SCANS = 20

#: Scans per inspection unless told: 1 s of data at the VLP-16's 600 rpm
#: (`scenarios.inspection.procedure.DEFAULT_SCANS`).
INSPECTION_SCANS = 10
#: A simulated line's misalignments: uniform within +-SPREAD x each limit
#: (`scenarios.inspection.line.DEFAULT_SPREAD`).
LINE_SPREAD = 1.3

#: Stop a reference (and the run) when this many scans in a row gave no pose and none at this
#: reference did: the board is not in view, and more scans will not bring it back
#: (`scenarios.config.MAX_CONSECUTIVE_FAILURES`).
MAX_CONSECUTIVE_FAILURES = 10

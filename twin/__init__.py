"""The bench, simulated or real, one folder per concern over the shared types of `twin.core`:

- `twin.core`: `Scan`, `Pose`, errors, the sensor's constants (imports nothing of the project);
- `twin.lidar`: the LiDAR's data path (packets, scans, pcap, UDP, capture sources);
- `twin.stage`: the stage controller (Grbl protocol, serial driver, motion model, simavr harness);
- `twin.sim`: the MuJoCo twin (bench parameters, physics, emulation, `BenchSim`, the wire server).
"""

"""The MuJoCo twin: bench parameters, physics, the ray-cast sensor emulation, `BenchSim` and the
wire-level server (`aimbench serve`).

Built on `twin.core`, `twin.lidar` (packets it sends) and `twin.stage` (the motion model, simavr).
"""

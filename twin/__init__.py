"""The bench, simulated or real: VLP-16 data path and emulation, MuJoCo twin, stage driver."""

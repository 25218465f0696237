"""Sweeps and studies on the simulated or the real bench, the result store, reports and the CLI."""

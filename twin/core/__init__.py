"""The shared types every layer speaks: `Scan`, `Pose`, `AimbenchError` and the sensor's constants.

Imports nothing else of the project (tests/test_layers.py keeps it so).
"""

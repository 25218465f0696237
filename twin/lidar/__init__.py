"""The LiDAR's data path: packets decoded and encoded, scans assembled, pcap files and live UDP.

Depends only on `twin.core`; never on the simulator or `scenarios`.
"""

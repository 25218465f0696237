"""What the data path reads and writes, by name only: the point-cloud drivers' conventions
(`twin.lidar.conventions.CONVENTIONS`) and the export formats (`twin.lidar.export`). The command
line offers them as choices without importing those modules (numpy; issue 38).
"""

#: The drivers whose point clouds aimbench reads, in `twin.lidar.conventions.CONVENTIONS`' order.
AIMBENCH = "aimbench"
VELODYNE_DECODER = "velodyne-decoder"
ROS_VELODYNE = "ros-velodyne"
NEBULA = "nebula"
CLOUD_CONVENTIONS = (AIMBENCH, VELODYNE_DECODER, ROS_VELODYNE, NEBULA)

#: The files scans are exported to, by extension (`twin.lidar.export.export_scans`).
EXPORT_FORMATS = (".npz", ".parquet", ".pcd", ".ply")

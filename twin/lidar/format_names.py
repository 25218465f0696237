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
#: Hesai's own ROS driver's PandarXT32 clouds (`twin.lidar.hesai_ros_clouds`), in Hesai's frame
#: (the driver's default) or turned to the ROS frame by its transform: read by their own
#: reader, not by `twin.lidar.conventions`.
HESAI_ROS = "hesai-ros"
HESAI_ROS_ROS_FRAME = "hesai-ros-ros-frame"
HESAI_CLOUD_CONVENTIONS = (HESAI_ROS, HESAI_ROS_ROS_FRAME)

#: The files scans are exported to, by extension (`twin.lidar.export.export_scans`).
EXPORT_FORMATS = (".npz", ".parquet", ".pcd", ".ply")

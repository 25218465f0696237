"""The sensors aimbench reads and emulates, by name only: the command line offers them as
``--model`` choices without importing their tables and decoders (numpy and the packet layouts,
about 0.15 s; issue 38: a command's parser within 0.5 s).

Each name is spelt here: `twin.core.sensors` (the Velodynes), `twin.lidar.hesai` and
`twin.lidar.ouster` build their models under these names.
"""

#: The Velodyne models, in `twin.core.sensors.MODELS`' order.
VLP16 = "VLP-16"
PUCK_HIRES = "Puck Hi-Res"
VLP32C = "VLP-32C"
HDL32E = "HDL-32E"
VELODYNE_NAMES = (VLP16, PUCK_HIRES, VLP32C, HDL32E)

#: The Hesai models, in `twin.lidar.hesai.HESAI_MODELS`' order.
PANDAR_XT32 = "PandarXT32"
PANDAR_QT128 = "PandarQT128"
HESAI_NAMES = (PANDAR_XT32, PANDAR_QT128)

#: Every Ouster model aimbench knows, by name.
OUSTER_MODELS = tuple(f"OS{k}-{b}" for k in (0, 1, 2) for b in (32, 64, 128))
#: The lidar modes (columns x frames a second) the Ouster sensors run.
LIDAR_MODES = ("512x10", "512x20", "1024x10", "1024x20", "2048x10")

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
#: The Ouster lidar packet profiles aimbench decodes (`twin.lidar.ouster.PROFILES`), the ones
#: the twin emits first (`aimbench simulate --udp-profile`): LEGACY, which every firmware
#: speaks, and the single, dual and low-bandwidth profiles of later firmware.
OUSTER_TWIN_PROFILES = ("LEGACY", "RNG19_RFL8_SIG16_NIR16", "RNG19_RFL8_SIG16_NIR16_DUAL",
                        "RNG15_RFL8_NIR8")
OUSTER_PROFILES = (*OUSTER_TWIN_PROFILES, "RNG15_RFL8_NIR8_DUAL", "FUSA_RNG15_RFL8_NIR8_DUAL")

"""aimbench: importing this package registers the Gymnasium environment ``aimbench/LidarAlign-v0``.

The code lives in the design's packages (`twin`, `align`, `scenarios`); this package exists so
that the distribution's own name is the import a user reaches for::

    import aimbench, gymnasium as gym
    env = gym.make("aimbench/LidarAlign-v0")     # or gym.make("aimbench:aimbench/LidarAlign-v0")
"""

from importlib import metadata

from scenarios.envs.lidar_align import ENV_ID, ENV_ID_NORMALIZED, LidarAlignEnv

__version__ = metadata.version("aimbench")
__all__ = ["ENV_ID", "ENV_ID_NORMALIZED", "LidarAlignEnv", "__version__"]

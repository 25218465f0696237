"""The headless OpenGL backends `twin.sim.render` tries, by name only: ``aimbench render
--backend`` offers them without importing MuJoCo (about 0.3 s; issue 38)."""

#: Headless backends in the order they are tried.
BACKENDS = ("egl", "osmesa", "glfw")

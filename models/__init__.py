"""MJCF models of the bench (data). `SCENE` is the composed scene; `SCENES` every scene a user
can pick by name (`twin.sim.params.BenchParams.scene`, a station's ``[twin] scene``,
``aimbench simulate --scene``)."""

from pathlib import Path

MODELS_DIR = Path(__file__).resolve().parent
SCENE = MODELS_DIR / "scene.xml"
#: The scenes by name: the bench alone (the paper's), and the bench in a cluttered lab.
SCENES = {"bench": SCENE, "lab": MODELS_DIR / "scene_lab.xml"}

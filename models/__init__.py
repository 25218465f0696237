"""MJCF models of the bench (data). `SCENE` is the composed scene."""

from pathlib import Path

MODELS_DIR = Path(__file__).resolve().parent
SCENE = MODELS_DIR / "scene.xml"

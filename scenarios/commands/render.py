"""`aimbench render`: a picture of an MJCF model, rendered offscreen (no display needed).

    aimbench render [MODEL.xml] --out bench.png [--camera NAME | --camera free]
                    [--lookat X,Y,Z] [--distance M] [--azimuth-deg A] [--elevation-deg E]
                    [--width 1280] [--height 720] [--keyframe NAME] [--backend egl|osmesa]

MODEL defaults to the bench scene (models/scene.xml). The camera: one of the model's (by name),
or ``free``, MuJoCo's free camera framing the whole model, which the ``--lookat``,
``--distance``, ``--azimuth-deg`` and ``--elevation-deg`` options move; without ``--camera``,
the model's first camera, or the free one when it has none (or when a free-camera option is
given). Rendering uses EGL (or OSMesa) with Mesa's software rasteriser, so it works over SSH and
in CI; ``tools/setup.sh`` installs the Debian packages.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import models  # the MJCF files' paths only
from scenarios import cliargs
from twin.core.errors import AimbenchError
from twin.sim.gl_backends import BACKENDS

# The renderer is imported by the functions that draw: it loads MuJoCo and numpy (about 0.3 s),
# which the parser does not need (issue 38).
if TYPE_CHECKING:
    from twin.sim.render import FreeCamera


def _floats(text: str, n: int, what: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != n:
        raise AimbenchError(f"{what} {text!r}: give {n} comma-separated numbers, e.g. 0,0,0.5")
    return values


def _camera(args: argparse.Namespace, names: list[str]) -> str | FreeCamera:
    from twin.sim.render import FreeCamera

    free = FreeCamera(
        lookat=_floats(args.lookat, 3, "--lookat") if args.lookat else None,
        distance=args.distance,
        azimuth=math.radians(args.azimuth_deg) if args.azimuth_deg is not None else None,
        elevation=math.radians(args.elevation_deg) if args.elevation_deg is not None else None)
    moved = free != FreeCamera()
    if args.camera is None:
        return free if moved or not names else names[0]
    if args.camera == "free":
        return free
    if moved:
        raise AimbenchError("--lookat, --distance, --azimuth-deg and --elevation-deg move the free "
                            f"camera; drop them or use --camera free instead of {args.camera!r}")
    if args.camera not in names:
        raise AimbenchError(f"no camera {args.camera!r} in the model; it has "
                            f"{', '.join(names) or 'none'} (or use --camera free)")
    return args.camera


def _load(path: Path):
    import mujoco

    if not path.is_file():
        raise AimbenchError(f"no model file {path}; give an MJCF file (default: the bench scene)")
    try:
        return mujoco.MjModel.from_xml_path(str(path))
    except ValueError as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else "compile error"
        raise AimbenchError(f"{path} does not compile as MJCF: {first}") from None


def run(args: argparse.Namespace) -> int:
    import matplotlib.image
    import mujoco

    from scenarios.progress import Bar
    from twin.sim.render import OffscreenRenderer, camera_names

    out = Path(args.out)
    if out.suffix.lower() != ".png":
        raise AimbenchError(f"--out {out}: the picture is written as PNG; name it *.png")
    if not out.parent.is_dir():
        raise AimbenchError(f"cannot write {out}: the folder {out.parent} does not exist")
    # seconds in all (the model's compile, a software OpenGL context, the picture): each step
    # is shown as it ends (scenarios/progress.py)
    with Bar(4, "render", unit="steps", every=1) as bar:
        model = _load(Path(args.model))
        data = mujoco.MjData(model)
        if args.keyframe is not None:
            key = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, args.keyframe)
            if key < 0:
                keys = [model.key(i).name for i in range(model.nkey)]
                raise AimbenchError(f"no keyframe {args.keyframe!r} in the model; it has "
                                    f"{', '.join(keys) or 'none'}")
            mujoco.mj_resetDataKeyframe(model, data, key)
        mujoco.mj_forward(model, data)
        camera = _camera(args, camera_names(model))
        bar.update(1, status="model compiled")
        with OffscreenRenderer(model, args.width, args.height, backend=args.backend) as renderer:
            bar.update(1, status=f"OpenGL context ({renderer.backend})")
            image = renderer.render(data, camera)
            backend = renderer.backend
            bar.update(1, status="rendered")
        matplotlib.image.imsave(out, image)
        bar.update(1, status=f"written to {out}")
    seen = f"camera {camera}" if isinstance(camera, str) else "the free camera"
    print(f"aimbench render: {args.model} from {seen}, {args.width} x {args.height} "
          f"({backend}) -> {out}", file=sys.stderr)
    return 0


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser("render", help="render an MJCF model (default: the bench) to a PNG "
                                      "offscreen, without a display",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", nargs="?", default=str(models.SCENE),
                   help="MJCF file (default: the bench scene, models/scene.xml)")
    p.add_argument("--out", required=True, help="PNG file to write")
    p.add_argument("--camera", help="a camera of the model by name, or 'free' (default: the "
                                    "model's first camera, else the free one)")
    p.add_argument("--lookat", metavar="X,Y,Z", help="free camera: the point it looks at, m")
    p.add_argument("--distance", type=cliargs.positive_float,
                   help="free camera: distance to that point, m")
    p.add_argument("--azimuth-deg", type=cliargs.finite_float, help="free camera: azimuth, deg")
    p.add_argument("--elevation-deg", type=cliargs.finite_float,
                   help="free camera: elevation, deg (negative looks down)")
    p.add_argument("--width", type=cliargs.positive_int, default=1280,
                   help="pixels (default %(default)s)")
    p.add_argument("--height", type=cliargs.positive_int, default=720,
                   help="pixels (default %(default)s)")
    p.add_argument("--keyframe", help="put the model in this keyframe first (default: qpos0)")
    p.add_argument("--backend", choices=BACKENDS,
                   help="OpenGL backend (default: MUJOCO_GL if set, else egl, then osmesa)")
    p.set_defaults(func=run)
    return p

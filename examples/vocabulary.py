"""Draws the contact sheet of the procedural vocabulary (examples/preview/vocabulary.png): three variants of each
marine animal and litter kind on a sand seabed, rendered by the real renderer with their textures, in clear water.

    python examples/vocabulary.py [--out examples/preview/vocabulary.png] [--tile 192x144]

Each tile is a frame of examples/urchins.yaml (its seabed, light and water, Jerlov II) with the frame's objects
replaced by variants 0-2 of one kind set side by side, and the camera moved to frame them; fish hang above the
seabed (their origin is their centre). The sheet is quantised to 256 colours to stay small.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from seasynth.service.spec.dataset import load_spec
from seasynth.worker.frame.function import PRESETS, RenderSession, scene_light
from seasynth.worker.render import Passes
from seasynth.worker.scene.assets.procedural import procedural_asset
from seasynth.worker.scene.materials import asset_material
from seasynth.worker.scene.poses import look_at_pose
from seasynth.worker.scene.sample import Placed

HERE = Path(__file__).resolve().parent
KINDS = ("starfish", "sea_cucumber", "scallop", "anemone", "sponge", "fish", "plastic_bottle",
         "glass_bottle", "can", "tyre", "rope", "net", "cinder_block", "pipe")
COLUMNS = 7


def tile_spec(width: int, height: int):
    """The tiles' scene: the urchins example on sand in Jerlov II at 5 m, the sun high."""
    return load_spec(HERE / "urchins.yaml", {"camera.width": width, "camera.height": height, "terrain.styles": ["sand"],
                                             "water.jerlov": ["II"], "water.depth_m": [5.0, 5.0],
                                             "lighting.sun_elevation_deg": [70.0, 70.0]})


def kind_tile(session: RenderSession, spec, kind: str) -> np.ndarray:
    """(h, w, 3) uint8 sRGB: variants 0-2 of `kind` in a row on frame 0's seabed."""
    scene = session.scene(spec, 0)
    assets = [procedural_asset(kind, v) for v in range(3)]
    size = max(float(np.ptp(a.mesh.vertices, axis=0).max()) for a in assets)
    objects = []
    for v, asset in enumerate(assets):
        x = (v - 1) * 1.15 * size
        ground = float(scene.terrain.height_at(np.array([[x, 0.0]]))[0])
        lift = 0.8 * float(np.ptp(asset.mesh.vertices[:, 2])) if kind == "fish" else 0.0
        yaw = 0.5 + 0.9 * v
        T = np.eye(4)
        T[:3, :3] = [[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0.0, 0.0, 1.0]]
        T[:3, 3] = [x, 0.0, ground + lift]
        objects.append(Placed(instance_id=v + 1, role="target", class_name="Thing", asset=asset, variant=v,
                              scale=1.0, world_from_obj=T, albedo_scale=np.ones(3, np.float32),
                              albedo_bias=np.zeros(3, np.float32), footprint_m=size,
                              material=asset_material(asset, v, spec)))
    target = np.array([0.0, 0.0, float(scene.terrain.height_at(np.zeros((1, 2)))[0]) + 0.2 * size])
    distance = 2.0 * size / math.tan(math.radians(spec.camera.hfov_deg) / 2.0)
    eye = target + distance * np.array([0.0, -math.cos(math.radians(35.0)), math.sin(math.radians(35.0))])
    scene = dataclasses.replace(scene, objects=tuple(objects), world_from_cam=look_at_pose(eye, target))
    result = session.renderer.render(session.view(spec, scene), session.draw_items(scene), scene_light(scene),
                                     scene.water, PRESETS[spec.quality], Passes(srgb8=True))
    return np.asarray(result.image)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=HERE / "preview" / "vocabulary.png")
    parser.add_argument("--tile", default="192x144", help="each tile's width x height in pixels")
    args = parser.parse_args()
    w, h = (int(n) for n in args.tile.split("x"))
    spec = tile_spec(w, h)
    rows = math.ceil(len(KINDS) / COLUMNS)
    sheet = Image.new("RGB", (COLUMNS * w, rows * h))
    with RenderSession() as session:
        for k, kind in enumerate(KINDS):
            tile = Image.fromarray(kind_tile(session, spec, kind))
            ImageDraw.Draw(tile).text((4, 2), kind, fill=(255, 255, 255))
            sheet.paste(tile, ((k % COLUMNS) * w, (k // COLUMNS) * h))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    sheet.quantize(256, dither=Image.Dither.NONE).save(args.out, optimize=True)
    print(f"{args.out}: {args.out.stat().st_size} bytes")


if __name__ == "__main__":
    main()

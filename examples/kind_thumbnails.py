"""Draws the playground's asset-picker thumbnails (api/static/playground/kinds/KIND.png): variants 0-2 of each
procedural kind on a sand seabed, rendered by the real renderer as examples/vocabulary.py draws its sheet.

    python examples/kind_thumbnails.py [--size 128x96]

They are committed rather than rendered by the API: the API has no GL (it never imports the worker), and one
small PNG per kind (about 11 KB, 256 colours) costs less than a render per process. Run it again when a kind's
meshes or textures change.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import get_args

from PIL import Image
from vocabulary import HERE, kind_tile, tile_spec

from seasynth.service.spec.scene import ProceduralTarget
from seasynth.worker.frame.function import RenderSession

OUT = HERE.parent / "api" / "static" / "playground" / "kinds"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--size", default="128x96", help="each thumbnail's width x height in pixels")
    args = parser.parse_args()
    w, h = (int(n) for n in args.size.split("x"))
    spec = tile_spec(w, h)
    args.out.mkdir(parents=True, exist_ok=True)
    with RenderSession() as session:
        for kind in get_args(ProceduralTarget):
            path = args.out / f"{kind}.png"
            Image.fromarray(kind_tile(session, spec, kind)).quantize(256, dither=Image.Dither.NONE).save(
                path, optimize=True)
            print(f"{path}: {path.stat().st_size} bytes")


if __name__ == "__main__":
    main()

"""YOLO detection export in Ultralytics' layout: images/{split}/*.png (or .jpg), labels/{split}/*.txt, data.yaml.

A label file has one line per object, `class cx cy w h`: the 0-based class (i = the spec's i-th target class,
then "distractor" with --distractors; a DontCare region, a target below the spec's label filters, has no line:
YOLO has no regions to ignore) and the box's centre and size normalised by the image's width and height,
each in [0, 1], with 10 decimals (the pixel edges come back to within 1e-6 px at 4096 px); a frame with no object
gets an empty file. data.yaml gives `path` (the export folder, absolute), `train`, `val`, `test` (image folders
relative to it; Ultralytics finds the labels by replacing images/ with labels/) and `names`.
"""

from __future__ import annotations

from seasynth.service.errors import ExportError
from seasynth.service.spec.outputs import SPLITS
from seasynth.worker.export.base import ExportInfo
from seasynth.worker.export.dataset import Frame
from seasynth.worker.export.files import make_dirs, place_file, write_atomic

DECIMALS = 10


def yolo_box(box: tuple[int, int, int, int], width: int, height: int) -> tuple[float, float, float, float]:
    """(cx, cy, w, h) in [0, 1] of a KITTI box (left, top, right, bottom) of inclusive 0-based pixel indices.

    In pixel-edge coordinates (pixel u covers [u, u + 1]) the box spans [left, right + 1] x [top, bottom + 1]:
    cx = (left + right + 1) / 2 / width, w = (right - left + 1) / width, and likewise along y with height.
    """
    left, top, right, bottom = box
    return ((left + right + 1) / (2 * width), (top + bottom + 1) / (2 * height),
            (right - left + 1) / width, (bottom - top + 1) / height)


def yolo_line(category: int, box: tuple[int, int, int, int], width: int, height: int) -> str:
    return " ".join([str(category), *(f"{v:.{DECIMALS}f}" for v in yolo_box(box, width, height))])


def data_yaml(info: ExportInfo) -> str:
    import yaml

    data = {"path": str(info.out), **{split: f"images/{split}" for split in SPLITS},
            "names": dict(enumerate(info.categories))}
    head = "# seasynth export, Ultralytics YOLO layout; `path` is absolute: edit it if the folder moves\n"
    return head + yaml.safe_dump(data, sort_keys=False, allow_unicode=True)


class YoloExporter:
    """Every split has its image and label folders, empty if no frame fell in it."""

    needs_masks = False  # boxes come from label_2 (distractors' from the masks, which the reader adds then)
    folder_globs = ("data.yaml",)

    def __init__(self) -> None:
        self._info: ExportInfo | None = None

    def frame_outputs(self, split: str, name: str) -> tuple[str, ...]:
        return (f"images/{split}/{name}{self._info.image_suffix}", f"labels/{split}/{name}.txt")

    def folder_outputs(self) -> tuple[str, ...]:
        return ("data.yaml",)

    def begin(self, info: ExportInfo) -> None:
        self._info = info
        make_dirs(*(info.out / kind / split for kind in ("images", "labels") for split in SPLITS))
        for split in SPLITS:  # Ultralytics' label caches (labels/{split}.cache) describe an earlier export's files
            try:
                (info.out / "labels" / f"{split}.cache").unlink(missing_ok=True)
            except OSError as err:
                raise ExportError(f"{info.out / 'labels'}/{split}.cache: cannot remove ({err.strerror or err})") \
                    from None

    def add(self, frame: Frame, split: str) -> None:
        image, labels = self.frame_outputs(split, frame.name)
        place_file(frame.image, self._info.out / image)
        text = "".join(yolo_line(o.category, o.box, frame.width, frame.height) + "\n" for o in frame.objects
                       if not o.ignore)  # a DontCare region has no YOLO form: left out
        write_atomic(self._info.out / labels, text.encode())

    def finish(self) -> None:
        write_atomic(self._info.out / "data.yaml", data_yaml(self._info).encode())

    def abort(self) -> None:
        pass  # every file is written whole by itself

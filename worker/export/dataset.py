"""Reading a local dataset for export: its record, which frames are complete, each frame's labels and masks."""

from __future__ import annotations

import contextlib
import io
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from seasynth import service
from seasynth.service.errors import AssetError, ExportError, SpecError
from seasynth.service.shards import FRAME_PARTS, SENSOR_PARTS, frame_file, frame_name, frame_parts
from seasynth.service.spec.dataset import DatasetSpec, parse_spec, spec_digest
from seasynth.worker.export.objects import FrameObject, label_objects, with_masks
from seasynth.worker.frame.function import DEPTH_SCALE, RenderSession, frame_paths
from seasynth.worker.frame.kitti import parse_calib
from seasynth.worker.scene.assets.user import check_assets

LOCAL_RECORD = "seasynth.json"  # written by `seasynth generate` (seasynth.worker.local.folder.RECORD)
FETCHED_RECORD = "manifest.json"  # written by `seasynth fetch`
MISSING_NAMED = 10  # missing files named in an error; the rest are counted

# Category indices: the spec's target classes in their order (0 .. n - 1), then (with distractors) "distractor" (n).
DISTRACTOR_NAME = "distractor"


@dataclass(frozen=True)
class LocalDataset:
    """A dataset folder and what its record says: the spec its frames were made from, and whether it is whole."""

    root: Path
    spec: DatasetSpec
    record_file: str  # LOCAL_RECORD or FETCHED_RECORD
    complete: bool  # the record's claim; the files are checked by scan_frames
    state: str  # the record's state ("complete", "incomplete", or a service state such as "running")
    code_version: str | None
    renderer: str | None

    @property
    def spec_sha256(self) -> str:
        return spec_digest(self.spec)


def open_local_dataset(root: Path) -> LocalDataset:
    """The dataset in `root`: a `seasynth generate` folder (seasynth.json) or a fetched one (manifest.json)."""
    root = Path(root)
    if not root.is_dir():
        raise ExportError(f"{root}: no such dataset folder")
    if (root / LOCAL_RECORD).is_file():
        name = LOCAL_RECORD
        record = _read_json(root / name)
        complete = record.get("state") == "complete"
    elif (root / FETCHED_RECORD).is_file():
        name = FETCHED_RECORD
        record = _read_json(root / name)
        complete = record.get("complete") is True
    else:
        raise ExportError(f"{root}: not a seasynth dataset (neither {LOCAL_RECORD} nor {FETCHED_RECORD} is there)")
    if not isinstance(record.get("spec"), dict):
        raise ExportError(f"{root / name}: field 'spec' is missing or not a mapping")
    try:
        spec = parse_spec(record["spec"], source=f"{root / name}: spec")
    except SpecError as err:
        raise ExportError(str(err)) from None
    if not spec.outputs.labels:
        raise ExportError(f"{root / name}: spec.outputs.labels is false, so the dataset has no label_2/ to export")
    return LocalDataset(root=root, spec=spec, record_file=name, complete=complete,
                        state=str(record.get("state")), code_version=record.get("code_version"),
                        renderer=record.get("renderer"))


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise ExportError(f"{path}: unreadable ({err})") from None
    if not isinstance(data, dict):
        raise ExportError(f"{path}: expected a JSON object, got {type(data).__name__}")
    return data


@dataclass(frozen=True)
class FrameScan:
    """Which frames have every file their spec's outputs call for."""

    complete: np.ndarray  # (frames,) bool, one byte per frame (1 MB at the 10^6-frame cap)
    missing_files: int  # files absent over all frames
    missing_named: tuple[str, ...]  # the first MISSING_NAMED of them, relative paths in frame order

    @property
    def frames_complete(self) -> int:
        return int(self.complete.sum())


def scan_frames(ds: LocalDataset) -> FrameScan:
    """Check every frame's files exist (the rule `generate --resume` uses: a file exists only once whole)."""

    complete = np.ones(ds.spec.frames, dtype=bool)
    missing, named = 0, []
    for i in range(ds.spec.frames):
        for rel in frame_paths(ds.spec, i):
            if not (ds.root / rel).is_file():
                complete[i] = False
                missing += 1
                if len(named) < MISSING_NAMED:
                    named.append(rel)
    return FrameScan(complete=complete, missing_files=missing, missing_named=tuple(named))


def incompleteness(ds: LocalDataset, scan: FrameScan) -> str | None:
    """Why the dataset is not whole (what its record says, which files are absent), or None if it is."""
    absent = ds.spec.frames - scan.frames_complete
    if ds.complete and absent == 0:
        return None
    said = "" if ds.complete else f"{ds.record_file} says it is incomplete (state {ds.state!r})"
    if absent == 0:
        return f"{ds.root}: {said}, though every frame's files are there (is a run still writing it?)"
    more = scan.missing_files - len(scan.missing_named)
    files = ", ".join(scan.missing_named) + (f" and {more} more" if more else "")
    return (f"{ds.root}: {said + '; ' if said else ''}{absent} of {ds.spec.frames} frames lack files "
            f"({scan.missing_files} missing: {files})")


@dataclass(frozen=True)
class Frame:
    """One complete frame, ready for an exporter. Objects: label lines in file order, then distractors (when
    asked) by ascending instance id."""

    index: int
    name: str  # KITTI's six-digit stem, "000123"
    image: Path  # the dataset's image_2 file (8-bit sRGB RGB; PNG, or JPEG with outputs.image_format jpeg)
    width: int  # px
    height: int  # px
    objects: tuple[FrameObject, ...]
    instance: np.ndarray | None  # (height, width) uint16 instance ids, 0 = terrain or water; None without masks
    # The frame's other files, for formats that carry the camera or depth (read with camera_projection,
    # camera_pose, depth_metres); None where the dataset does not have that output.
    calib: Path | None = None  # calib/{name}.txt
    meta: Path | None = None  # meta/{name}.json
    depth: Path | None = None  # depth/{name}.png
    # The sonar and navigation sensors' files (seasynth.worker.sensors.outputs), by folder: "fls", "fls_fan", "nav", ...
    sensor_files: dict[str, Path] = field(default_factory=dict)


class FrameReader:
    """Reads frames of a dataset; with masks, instance ids come from instance/ + meta/, else by re-rendering.

    Re-rendering (a dataset without instance/ or meta/) renders each frame again with outputs.instance and
    outputs.meta on, in one GL session of this process, and refuses a frame whose re-rendered image_2 file or
    label_2 text differs by one byte from the dataset's (another code version, renderer or user file).
    """

    def __init__(self, ds: LocalDataset, *, masks: bool, distractors: bool, platform: str = "egl") -> None:
        self.ds = ds
        self.masks = masks or distractors  # distractors have no label line: their boxes come from the masks
        self.distractors = distractors
        self._platform = platform
        self._session = None
        self._stack = contextlib.ExitStack()
        o = ds.spec.outputs
        self.renders = self.masks and not (o.instance and o.meta)
        self._render_spec = mask_spec(ds.spec)

    def __enter__(self) -> FrameReader:
        if self.renders:
            self._open_session()
        return self

    def __exit__(self, *exc: object) -> None:
        self._session = None
        self._stack.close()

    def _open_session(self) -> None:
        uploaded = [field for field, ref in self.ds.spec.file_refs() if ref.asset_id is not None]
        if uploaded:
            raise ExportError(f"{self.ds.root}: no instance/ to take masks from, and its spec names uploaded "
                              f"assets ({', '.join(uploaded)}) that cannot be re-rendered here; generate it with "
                              "outputs.instance on")
        try:
            check_assets(self.ds.spec)
        except AssetError as err:
            raise ExportError(f"{self.ds.root}: cannot re-render its instance masks: {err}") from None
        self._session = self._stack.enter_context(RenderSession(platform=self._platform))

    def read(self, index: int) -> Frame:
        """Frame `index` (which must be complete); ExportError naming the file at fault if it is inconsistent."""
        root = self.ds.root
        label_bytes = _read_bytes(root / frame_file("label", index))
        masks = None
        if self.masks:
            if self.renders:
                masks = (*self._render(index, label_bytes), f"re-rendered {frame_file('instance', index)}")
            else:
                where = str(root / frame_file("instance", index))
                masks = (_read_instance(Path(where)), _read_json(root / frame_file("meta", index)), where)
        return frame_of(self.ds.spec, root, index, label_bytes, masks, self.distractors)

    def _render(self, index: int, label_bytes: bytes) -> tuple[np.ndarray, dict]:
        """(instance ids (h, w) uint16, meta) of frame `index` rendered again, once its image and labels are
        checked to be the dataset's bytes."""
        try:
            files = self._session.frame_files(self._render_spec, index)
        except OSError as err:  # an asset file the session cannot read
            raise ExportError(f"{self.ds.root}: cannot re-render frame {index}: {err}") from None
        rel_image = frame_file("image", index, self.ds.spec.outputs.image_suffix)
        image = _read_bytes(self.ds.root / rel_image)
        for rel, theirs in ((rel_image, image), (frame_file("label", index), label_bytes)):
            if files[rel] != theirs:
                raise ExportError(
                    f"{self.ds.root / rel}: the frame re-rendered to obtain its instance masks differs from the "
                    f"dataset's file, so masks drawn now need not match its pixels (dataset: code version "
                    f"{self.ds.code_version}, renderer {self.ds.renderer!r}; here: code version "
                    f"{_code_version()}, renderer {self._session.renderer_name!r}); export it where it was made, "
                    "or generate it with outputs.instance on"
                )
        rel_instance = frame_file("instance", index)
        instance = decode_instance(files[rel_instance], f"re-rendered {rel_instance}")
        return instance, json.loads(files[frame_file("meta", index)])


def mask_spec(spec: DatasetSpec) -> DatasetSpec:
    """`spec` with the outputs instance masks are read from switched on (instance/, meta/, label_2/). Its frames'
    image_2, label_2 and calib bytes are those of `spec` (label_2 already renders the instance ids)."""
    o = spec.outputs
    return spec.model_copy(update={"outputs": o.model_copy(update={"instance": True, "meta": True, "labels": True})})


def frame_of(spec: DatasetSpec, root: Path, index: int, label_bytes: bytes,
             masks: tuple[np.ndarray, dict, str] | None, distractors: bool) -> Frame:
    """Frame `index` of the KITTI files under `root`, labelled as `spec` says.

    label_bytes: its label_2 file's bytes; masks: (instance ids (h, w) uint16, its meta record, where they came
    from, for errors), or None to read no masks. The frame's meta and depth paths follow spec.outputs.
    """
    def path(part: str) -> Path:
        return root / frame_file(part, index, spec.outputs.image_suffix)

    label_path = path("label")
    try:
        label_text = label_bytes.decode("utf-8")
    except UnicodeDecodeError as err:
        raise ExportError(f"{label_path}: not UTF-8 text ({err.reason} at byte {err.start})") from None
    objects = label_objects(label_path, label_text, spec.class_names)
    instance = None
    if masks is not None:
        instance, meta, where = masks
        if instance.shape != (spec.camera.height, spec.camera.width):
            raise ExportError(f"{where}: shape {instance.shape}, the spec says "
                              f"{spec.camera.height}x{spec.camera.width} (height x width)")
        objects = with_masks(objects, instance, meta, where, label_path, distractors, spec.class_names)
    o = spec.outputs
    return Frame(index=index, name=frame_name(index), image=path("image"), width=spec.camera.width,
                 height=spec.camera.height, objects=tuple(objects), instance=instance,
                 calib=path("calib"), meta=path("meta") if o.meta else None,
                 depth=path("depth") if o.depth else None,
                 sensor_files={FRAME_PARTS[p][0]: path(p) for p in frame_parts(spec) if p in SENSOR_PARTS})


def camera_projection(path: Path) -> np.ndarray:
    """(3, 4) float64 P2 of a calib file: K [I | 0] of the frame's camera, pixels."""

    try:
        text = _read_bytes(path).decode("utf-8")
        p2 = parse_calib(text).get("P2")
    except (UnicodeDecodeError, ValueError) as err:
        raise ExportError(f"{path}: not a KITTI calib file ({err})") from None
    if p2 is None or p2.shape != (3, 4) or not np.isfinite(p2).all():
        raise ExportError(f"{path}: no finite 12-number P2 line")
    return p2


def camera_pose(path: Path) -> np.ndarray:
    """(4, 4) float64 world_from_camera (KITTI camera axes: x right, y down, z forward) of a meta file."""
    try:
        pose = np.array(_read_json(path)["camera"]["pose_world_from_camera"], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as err:
        raise ExportError(f"{path}: no camera.pose_world_from_camera ({err})") from None
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise ExportError(f"{path}: camera.pose_world_from_camera is not a finite 4x4 matrix")
    return pose


def depth_metres(path: Path, width: int, height: int) -> np.ndarray:
    """(height, width) float32 z-depth in metres of a KITTI depth PNG (uint16 metres * 256); NaN where 0."""
    from PIL import Image, UnidentifiedImageError


    try:
        with Image.open(io.BytesIO(_read_bytes(path))) as img:
            if img.mode != "I;16":
                raise ExportError(f"{path}: PNG mode {img.mode}, expected 16-bit greyscale (I;16) depth")
            raw = np.asarray(img).astype(np.uint16, copy=False)
    except (OSError, UnidentifiedImageError) as err:
        raise ExportError(f"{path}: cannot decode ({err})") from None
    if raw.shape != (height, width):
        raise ExportError(f"{path}: shape {raw.shape}, the spec says {height}x{width} (height x width)")
    depth = raw.astype(np.float32) / np.float32(DEPTH_SCALE)  # exact: 16-bit integers / 2^8
    depth[raw == 0] = np.nan
    return depth


def _code_version() -> str:
    return service.__version__


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as err:
        raise ExportError(f"{path}: unreadable ({err.strerror or err})") from None


def _read_instance(path: Path) -> np.ndarray:
    return decode_instance(_read_bytes(path), str(path))


def decode_instance(data: bytes, where: str) -> np.ndarray:
    """(h, w) uint16 instance ids of a 16-bit greyscale PNG."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as img:
            if img.mode != "I;16":
                raise ExportError(f"{where}: PNG mode {img.mode}, expected 16-bit greyscale (I;16) instance ids")
            ids = np.asarray(img)
    except (OSError, UnidentifiedImageError) as err:
        raise ExportError(f"{where}: cannot decode ({err})") from None
    return ids.astype(np.uint16, copy=False)

"""Wavefront MTL material libraries, as far as the mesh loader reads them (seasynth.worker.scene.assets.surfaces)
and the upload check checks them (seasynth.service.textures): each material's Kd, map_Kd and bump map with its -bm
scale."""

from __future__ import annotations

from dataclasses import dataclass

from seasynth.service.errors import AssetError

# Map options and how many values each takes (-o, -s and -t take 1 to 3 numbers).
MTL_OPTIONS = {"-bm": 1, "-blendu": 1, "-blendv": 1, "-boost": 1, "-cc": 1, "-clamp": 1, "-imfchan": 1, "-mm": 2,
               "-texres": 1, "-type": 1, "-o": 3, "-s": 3, "-t": 3}


@dataclass(frozen=True)
class MtlMaterial:
    """What an MTL says of one material, as far as it is read."""

    index: int  # order in the library
    kd: tuple[float, ...] | None
    map_kd: str | None  # file names as written
    bump: str | None
    bump_scale: float


def map_file(tokens: list[str]) -> tuple[str, dict[str, list[str]]]:
    """(file name, options) of an MTL map statement's arguments: `-bm 0.5 bump.png` -> ('bump.png', {'-bm': ['0.5']})."""
    options: dict[str, list[str]] = {}
    k = 0
    while k < len(tokens) and tokens[k].lower() in MTL_OPTIONS:
        option, k = tokens[k].lower(), k + 1
        values = []
        while k < len(tokens) and len(values) < MTL_OPTIONS[option]:
            if option in ("-o", "-s", "-t") and values and not _is_number(tokens[k]):
                break
            values.append(tokens[k])
            k += 1
        options[option] = values
    return " ".join(tokens[k:]), options


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def read_mtl(text: str, where: str) -> dict[str, MtlMaterial]:
    """The materials of an MTL library by name (trimesh's reading: `newmtl` takes the rest of its line)."""
    found: dict[str, MtlMaterial] = {}
    name, fields = None, {}
    count = [0]  # newmtl statements so far: a name given twice keeps its last definition, under a fresh index

    def close() -> None:
        if name is not None:
            found[name] = MtlMaterial(count[0], **fields)
            count[0] += 1

    for line in text.splitlines():
        split = line.strip().split()
        if len(split) <= 1:
            continue
        key = split[0].lower()
        if key == "newmtl":
            close()
            name, fields = " ".join(split[1:]), {"kd": None, "map_kd": None, "bump": None, "bump_scale": 1.0}
        elif name is None:
            continue
        elif key == "kd":
            try:  # as trimesh: a Kd that is not numbers is left out
                fields["kd"] = tuple(float(x) for x in split[1:4])
            except ValueError:
                pass
        elif key == "map_kd":
            fields["map_kd"] = map_file(split[1:])[0]
        elif key in ("map_bump", "bump"):
            file, options = map_file(split[1:])
            try:
                scale = float(options.get("-bm", ["1"])[0])
            except ValueError:
                raise AssetError(f"{where}: material {name!r}: -bm {options['-bm'][0]!r} is not a number") from None
            fields.update(bump=file, bump_scale=scale)
    close()
    return found

"""Converged path-traced references, kept apart from scoring.

A multiply-scattering sun through metres of forward-scattering water (HG g ~ 0.9) converges slowly: at 160x120 a
path-traced frame needs about 10^5 samples per pixel before its noise floor clears 40 dB, hours on two cores. So a
reference is rendered once, anywhere Mitsuba runs (its `cuda_ad_rgb` variant on a GPU host, or `llvm_ad_rgb` on
many cores), stored beside the fidelity table, and scored on any machine. A reference is tied to its exported scene
by the scene's digest (`scene_digest`) and, for machines whose float kernels round the export's last bits otherwise
(BLAS and SIMD paths follow the CPU), by its fingerprint (`scene_fingerprint`): change the scene and the stored
reference no longer matches (`same_scene`).

This module needs only numpy and Mitsuba (not the rest of seasynth), so a render host needs nothing else:

    python -m seasynth.bench.reference DIR --spp 131072 --variant cuda_ad_rgb

renders each DIR/NAME.scene.npz into DIR/NAME.ref.npz (two independent halves, their spp, variant, seconds).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import time
from pathlib import Path
from typing import BinaryIO

import numpy as np

from seasynth.bench import pathtracer
from seasynth.bench.pathtracer import PTLamp, PTLens, PTMesh, PTScene, PTSpheres
from seasynth.bench.pathtracer_textures import PTMaterial, procedural_image

SCENE_SUFFIX = ".scene.npz"
REF_SUFFIX = ".ref.npz"


def _scene_arrays(scene: PTScene) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for f in dataclasses.fields(PTScene):
        value = getattr(scene, f.name)
        if f.name == "meshes":
            for i, m in enumerate(value):
                out[f"mesh{i}_vertices"] = np.asarray(m.vertices, np.float32)
                out[f"mesh{i}_faces"] = np.asarray(m.faces, np.uint32)
                out[f"mesh{i}_albedo"] = np.asarray(m.albedo, np.float32)
                out[f"mesh{i}_instance_id"] = np.asarray(m.instance_id, np.int64)
                if m.material is not None:
                    out.update(_material_arrays(m.material, f"mesh{i}_mat_"))
        elif f.name == "slab" and value is None:  # no port: the scene's arrays (and digest) as before ports
            continue
        elif f.name == "spheres":  # none: no arrays, so scenes without them keep their digests
            if value is not None:  # centres as the path tracer takes them (float32, as mesh vertices): no digest
                out.update({f"spheres_{g.name}": np.asarray(getattr(value, g.name),  # moves on a last-bit change
                                                            np.float64 if g.name == "radii" else np.float32)
                            for g in dataclasses.fields(PTSpheres)})
        elif f.name == "lens":  # absent for a pinhole, so the digests of scenes from before lenses stay
            if value is not None:
                out.update({f"lens_{g.name}": np.asarray(getattr(value, g.name), np.float64)
                            for g in dataclasses.fields(PTLens)})
        elif f.name == "lamps":
            for i, lamp in enumerate(value):
                for g in dataclasses.fields(PTLamp):
                    out[f"lamp{i}_{g.name}"] = np.asarray(getattr(lamp, g.name), np.float64)
        else:
            out[f.name] = np.asarray(value, np.int64 if f.name in ("width", "height") else np.float64)
    return out


def scene_digest(scene: PTScene) -> str:
    """sha256 over every array of the scene, in a fixed order (names, dtypes, shapes and bytes)."""
    h = hashlib.sha256()
    for name, a in sorted(_scene_arrays(scene).items()):
        a = np.ascontiguousarray(a)
        h.update(f"{name}:{a.dtype.str}:{a.shape};".encode())
        h.update(a.tobytes())
    return h.hexdigest()


FINGERPRINT_RUNS = 16  # a float array's sums are taken over this many equal runs of its flattened elements
FINGERPRINT_RTOL = 1e-6  # of a run's magnitude: 8 float32 steps on every element move a run's sum by <= 4.8e-7
FINGERPRINT_ATOL = 1e-12  # where a value sits at zero (metres, radiance, 1/m: far below anything rendered)


def scene_fingerprint(scene: PTScene) -> dict[str, list]:
    """The scene's arrays (as `scene_digest` takes them) up to their floats' last bits: per float array its dtype,
    shape and, over FINGERPRINT_RUNS equal runs of its elements, each run's sum and sum of magnitudes (float64);
    per other array (faces, ids, image digests, names) its dtype, shape and sha256."""
    out = {}
    for name, a in sorted(_scene_arrays(scene).items()):
        head = [a.dtype.str, list(a.shape)]
        if a.dtype.kind == "f":
            runs = np.array_split(a.astype(np.float64).ravel(), min(FINGERPRINT_RUNS, max(a.size, 1)))
            out[name] = head + [[float(r.sum()) for r in runs], [float(np.abs(r).sum()) for r in runs]]
        else:
            out[name] = head + [hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()]
    return out


def fingerprints_agree(a: dict[str, list], b: dict[str, list], rtol: float = FINGERPRINT_RTOL,
                       atol: float = FINGERPRINT_ATOL) -> bool:
    """Same arrays, dtypes, shapes and exact parts; each float run's sum and magnitude within rtol of the larger of
    its magnitude and the array's mean run magnitude, plus atol."""
    if a.keys() != b.keys():
        return False
    for name, x in a.items():
        y = b[name]
        if x[:2] != y[:2] or len(x) != len(y) or (len(x) == 3 and x[2] != y[2]):
            return False
        if len(x) == 4:
            (sa, ma), (sb, mb) = (np.array(x[2:]), np.array(y[2:]))
            scale = np.maximum(np.maximum(ma, mb), max(ma.mean(), mb.mean()))
            if np.any(np.abs(sa - sb) > rtol * scale + atol) or np.any(np.abs(ma - mb) > rtol * scale + atol):
                return False
    return True


def same_scene(ref: Reference, scene: PTScene) -> bool:
    """Whether `ref` was rendered for `scene`: the same digest, or the same fingerprint (the export made again on a
    machine whose float kernels round otherwise)."""
    if ref.scene_sha256 == scene_digest(scene):
        return True
    return ref.scene_fingerprint is not None and fingerprints_agree(ref.scene_fingerprint, scene_fingerprint(scene))


def stamp_fingerprint(path: Path, scene: PTScene, *, check_digest: bool = True) -> None:
    """Adds `scene`'s fingerprint to the stored reference at `path`, which must have been rendered for this scene:
    the same digest, or (check_digest=False) the scene exported again on a machine whose float kernels round
    otherwise, shown to be the same by other means."""
    ref = load_reference(path)
    if check_digest and ref.scene_sha256 != scene_digest(scene):
        raise ValueError(f"{path}: rendered for another scene (sha256 {ref.scene_sha256[:12]}, not "
                         f"{scene_digest(scene)[:12]})")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["meta"]))
    arrays["meta"] = np.array(json.dumps({**meta, "scene_fingerprint": scene_fingerprint(scene)}))
    np.savez_compressed(path, **arrays)


def save_scene(scene: PTScene, path: Path) -> None:
    np.savez_compressed(path, **_scene_arrays(scene))


def load_scene(path: Path) -> PTScene:
    with np.load(path) as z:
        a = {k: z[k] for k in z.files}
    meshes = tuple(PTMesh(a[f"mesh{i}_vertices"], a[f"mesh{i}_faces"], a[f"mesh{i}_albedo"],
                          int(a[f"mesh{i}_instance_id"]), _material(a, f"mesh{i}_mat_"))
                   for i in range(sum(k.endswith("_faces") for k in a)))
    lamps = tuple(PTLamp(**{g.name: (float(a[f"lamp{i}_{g.name}"]) if a[f"lamp{i}_{g.name}"].ndim == 0
                                     else a[f"lamp{i}_{g.name}"]) for g in dataclasses.fields(PTLamp)})
                  for i in range(sum(k.endswith("_intensity_rgb") for k in a)))
    scalars = {"width": int, "height": int, "g": float, "surface_z": float, "sky_cone_deg": float}
    spheres = (PTSpheres(**{g.name: a[f"spheres_{g.name}"] for g in dataclasses.fields(PTSpheres)})
               if "spheres_centres" in a else None)
    rest = {f.name: (scalars[f.name](a[f.name]) if f.name in scalars else a[f.name])
            for f in dataclasses.fields(PTScene) if f.name not in ("meshes", "lamps", "spheres", "lens") and f.name in a}
    lens = PTLens(**{g.name: float(a[f"lens_{g.name}"]) for g in dataclasses.fields(PTLens)}) \
        if "lens_focus_m" in a else None
    return PTScene(meshes=meshes, lamps=lamps, spheres=spheres, lens=lens, **rest)


IMAGES = ("base", "normal")


def _material_arrays(m: PTMaterial, prefix: str) -> dict[str, np.ndarray]:
    """A material's fields; a procedural image as its name and the sha256 of its pixels (made again on loading)."""
    out = {}
    for g in dataclasses.fields(PTMaterial):
        value = getattr(m, g.name)
        if value is None:
            continue
        if g.name in IMAGES and getattr(m, f"{g.name}_key") is not None:
            out[f"{prefix}{g.name}_sha256"] = np.asarray(hashlib.sha256(np.ascontiguousarray(value)).hexdigest())
        else:
            out[prefix + g.name] = np.asarray(value)
    return out


def _material(a: dict[str, np.ndarray], prefix: str) -> PTMaterial | None:
    if f"{prefix}mapping" not in a:
        return None
    kinds = {"base_gain": float, "normal_scale": float, "metallic": float, "triplanar_per_m": float, "mapping": str,
             "base_key": str, "normal_key": str}
    fields = {g.name: (kinds[g.name](a[prefix + g.name]) if g.name in kinds and prefix + g.name in a
                       else a.get(prefix + g.name)) for g in dataclasses.fields(PTMaterial)}
    for name in IMAGES:
        if fields[f"{name}_key"] is not None:
            pixels = procedural_image(fields[f"{name}_key"])
            if hashlib.sha256(np.ascontiguousarray(pixels)).hexdigest() != str(a[f"{prefix}{name}_sha256"]):
                raise ValueError(f"{fields[f'{name}_key']}: made again here, its pixels differ from the exported "
                                 "scene's (another numpy?)")
            fields[name] = pixels
    return PTMaterial(**fields)


@dataclasses.dataclass(frozen=True)
class Reference:
    """Two independent path-traced halves (h, w, 3) float32 linear radiance, each of `spp` samples per pixel."""

    halves: tuple[np.ndarray, np.ndarray]
    spp: int
    variant: str
    seconds: float  # both halves together
    host: str
    scene_sha256: str
    seed_bases: tuple[int, ...] = (0,)  # half k of base s was seeded with 2 s + k
    lamp_housing_m: float = 0.0  # radius of the water-free sphere round each lamp (pathtracer._lamp); 0: none
    scene_fingerprint: dict[str, list] | None = None  # scene_fingerprint; None in references from before it

    @property
    def mean(self) -> np.ndarray:
        return (self.halves[0] + self.halves[1]) / 2


def render_reference(scene: PTScene, spp: int, variant: str = pathtracer.VARIANT, host: str = "",
                     seed_base: int = 0, lamp_housing_m: float = 0.0) -> Reference:
    halves, seconds = [], 0.0
    for k in (0, 1):
        t0 = time.perf_counter()
        halves.append(pathtracer.render(scene, spp, seed=2 * seed_base + k, variant=variant,
                                        lamp_housing_m=lamp_housing_m))
        seconds += time.perf_counter() - t0
    return Reference(tuple(halves), spp, variant, seconds, host, scene_digest(scene), (seed_base,),
                     lamp_housing_m if scene.lamps else 0.0, scene_fingerprint(scene))


def merge(a: Reference, b: Reference) -> Reference:
    """One reference of both renders' samples (each half the spp-weighted mean); they must share the scene and
    have been seeded apart."""
    if a.scene_sha256 != b.scene_sha256:
        raise ValueError("merge: the references were rendered for different scenes")
    if a.lamp_housing_m != b.lamp_housing_m:
        raise ValueError(f"merge: lamp housings differ ({a.lamp_housing_m} m and {b.lamp_housing_m} m)")
    if set(a.seed_bases) & set(b.seed_bases):
        raise ValueError(f"merge: both used seed bases {sorted(set(a.seed_bases) & set(b.seed_bases))}")
    n = a.spp + b.spp
    halves = tuple(((a.spp * x.astype(np.float64) + b.spp * y) / n).astype(np.float32)
                   for x, y in zip(a.halves, b.halves))
    variant = a.variant if a.variant == b.variant else f"{a.variant}+{b.variant}"
    host = a.host if a.host == b.host else f"{a.host}; {b.host}"
    return Reference(halves, n, variant, a.seconds + b.seconds, host, a.scene_sha256, a.seed_bases + b.seed_bases,
                     a.lamp_housing_m, a.scene_fingerprint or b.scene_fingerprint)


def budget_spp(scene: PTScene, seconds: float, variant: str, lamp_housing_m: float = 0.0) -> int:
    """Samples per pixel per half that fill about `seconds` for both halves, from one timed call (whole calls)."""
    per_call = max(1, pathtracer.MAX_SAMPLES_PER_CALL[variant] // (scene.width * scene.height))
    pathtracer.render(scene, 1, seed=99, variant=variant, lamp_housing_m=lamp_housing_m)  # compiles the kernels
    t0 = time.perf_counter()
    pathtracer.render(scene, per_call, seed=98, variant=variant, lamp_housing_m=lamp_housing_m)
    calls = int(seconds / 2 / max(time.perf_counter() - t0, 1e-3))
    return per_call * max(1, calls)


def save_reference(ref: Reference, path: Path | BinaryIO) -> None:
    meta = {"spp": ref.spp, "variant": ref.variant, "seconds": ref.seconds, "host": ref.host,
            "scene_sha256": ref.scene_sha256, "seed_bases": list(ref.seed_bases), "lamp_housing_m": ref.lamp_housing_m}
    if ref.scene_fingerprint is not None:
        meta["scene_fingerprint"] = ref.scene_fingerprint
    np.savez_compressed(path, half0=ref.halves[0], half1=ref.halves[1], meta=np.array(json.dumps(meta)))


def load_reference(path: Path) -> Reference:
    """A stored reference; halves stored as float16 (a compact copy: `compact`) come back as float32."""
    with np.load(path) as z:
        meta = json.loads(str(z["meta"]))
        meta["seed_bases"] = tuple(meta.get("seed_bases", (0,)))
        return Reference((z["half0"].astype(np.float32), z["half1"].astype(np.float32)), **meta)


def compact(path: Path) -> None:
    """Rewrites a stored reference with float16 halves, half its size: radiances from 6e-5 up keep 0.05% (11 bits of
    mantissa), smaller ones 6e-8 absolute (subnormals); the 7 references compacted so moved their 8-bit sRGB mean by
    at most one code, where it sat on a rounding boundary, far below the halves' own noise."""
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    for k in ("half0", "half1"):
        if np.abs(arrays[k]).max() > 6e4:
            raise ValueError(f"{path}: {k} exceeds float16's range")
        arrays[k] = arrays[k].astype(np.float16)
    np.savez_compressed(path, **arrays)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description="Render DIR/*.scene.npz into DIR/*.ref.npz with Mitsuba 3.")
    p.add_argument("dir", type=Path)
    size = p.add_mutually_exclusive_group(required=True)
    size.add_argument("--spp", type=int, help="samples per pixel of each of the two halves")
    size.add_argument("--seconds", type=float, help="a time budget per scene: spp from a timed first call")
    p.add_argument("--variant", default=pathtracer.VARIANT, help="llvm_ad_rgb (CPU) or cuda_ad_rgb (GPU)")
    p.add_argument("--host", default="", help="a description of the machine, recorded with the reference")
    p.add_argument("--out", type=Path, help="folder for the references (default: DIR)")
    p.add_argument("--seed-base", type=int, default=0, help="halves are seeded 2 BASE and 2 BASE + 1")
    p.add_argument("--merge-with", type=Path, help="a folder of references: each one found is merged in")
    p.add_argument("--lamp-housing-m", type=float, default=0.0,
                   help="radius of a water-free sphere round each lamp, bounding its fireflies (0: none)")
    args = p.parse_args(argv)
    out = args.out or args.dir
    out.mkdir(parents=True, exist_ok=True)
    for path in sorted(args.dir.glob(f"*{SCENE_SUFFIX}")):
        name = path.name[: -len(SCENE_SUFFIX)]
        scene = load_scene(path)
        spp = args.spp or budget_spp(scene, args.seconds, args.variant, args.lamp_housing_m)
        ref = render_reference(scene, spp, args.variant, args.host, args.seed_base, args.lamp_housing_m)
        earlier = args.merge_with / f"{name}{REF_SUFFIX}" if args.merge_with else None
        if earlier is not None and earlier.exists():
            ref = merge(load_reference(earlier), ref)
        save_reference(ref, out / f"{name}{REF_SUFFIX}")
        print(json.dumps({"config": name, "spp": ref.spp, "seconds": round(ref.seconds, 2),
                          "seed_bases": list(ref.seed_bases)}), flush=True)


if __name__ == "__main__":
    main()

"""The spec reference (docs/spec.md), generated from the pydantic models so that it cannot drift from them.

    python -m seasynth.service.spec.reference > docs/spec.md     # write it
    python -m seasynth.service.spec.reference --check docs/spec.md  # exit 1 if the file is not what it would write

Each model of DatasetSpec gets a section: a table of its fields (type, default, constraints, description) and the
checks its validators make across fields. A field's description is its Field(description=...), else the comments
written beside it in the model's source (the spec's models document their fields that way), else the first
sentence of its section's docstring. A validator with neither an entry below nor a docstring stops the generator,
so a new check cannot go undocumented.
"""

from __future__ import annotations

import ast
import inspect
import io
import json
import sys
import textwrap
import tokenize
import types
from collections.abc import Callable, Iterator
from typing import Annotated, Any, Literal, Union, get_args, get_origin

from pydantic import BaseModel
from pydantic.fields import FieldInfo

from seasynth.service.spec.dataset import MAX_SHARD_MEGAPIXELS, DatasetSpec
from seasynth.service.spec.scene import MAX_OBJECTS
from seasynth.service.spec.sensors import (
    MAX_FLS_FAN_PIXELS,
    MAX_FLS_RANGE_M,
    MAX_FLS_RENDER_PIXELS,
    MAX_FLS_RENDER_SIDE,
)
from seasynth.service.spec.types import MAX_MAGNITUDE, SpecModel
from seasynth.service.water import JERLOV_TYPES

# What each value validator (AfterValidator) checks, by function name. `ordered` and `bounded` make a field an
# interval or a vector (the preamble states their rule once); a lambda calling `within(v, lo, hi)` is read off its
# constants.
VALUE_CHECKS: dict[str, str] = {
    "ordered": "",
    "bounded": "",
    "nonneg": "min >= 0",
    "positive": "min > 0",
    "_count_range": f"0 <= min <= max <= {MAX_OBJECTS}",
    "_kitti_token": "no whitespace or control character (one KITTI label field); not `DontCare`",
    "_classes_fit": f"class names unique; the classes' count maxima (times school sizes) total <= {MAX_OBJECTS}",
    "_fls_range": f"0 < min < max <= {MAX_FLS_RANGE_M:g}",
}

# What each field validator and model validator checks, by qualified name.
FIELD_CHECKS: dict[str, str] = {
    "Camera._near_before_far": "near < far",
    "Water._known_types": "each one of " + ", ".join(f"`{t}`" for t in JERLOV_TYPES),
    "FLS._fan_fits": f"the fan image at most {MAX_FLS_FAN_PIXELS:,} pixels",
    "Outputs._export_needs_labels": "needs `labels: true`",
    "Outputs._quality_needs_jpeg": "other than the default only with `image_format: jpeg`",
    "Outputs._split": "three numbers >= 0 summing to 1",
}
MODEL_CHECKS: dict[str, str] = {
    "Box._check": "min <= max on each axis.",
    "Camera._one_projection": "`hfov_deg` or `intrinsics`, not both; `intrinsics` must see less than 170 deg on "
                              "each axis.",
    "FileRef._exactly_one": "Exactly one of `path`, `asset_id`.",
    "AssetRef._exactly_one": "Exactly one of `procedural`, `path`, `asset_id`.",
    "Lamp._check": "`direction` is not the zero vector; `beam_width_deg` <= `cutoff_deg`; `colour` >= 0 per channel.",
    "RGBInterval._check": "0 <= min <= max per channel.",
    "Water._described": "Fields of the other model are refused; with no `jerlov` types, `absorption` and "
                        "`scattering` (physical) or `beta_D` and `B_inf` (paper) must be given. `particles` need "
                        "`enabled` water, and a `density_per_m3` where no Jerlov type gives the default.",
    "FLS._beam_narrower_than_fan": f"`beam_width_deg` < `horizontal_aperture_deg`; the sonar's render is at most "
                                   f"{MAX_FLS_RENDER_SIDE} pixels a side and {MAX_FLS_RENDER_PIXELS:,} in all.",
    "DatasetSpec._resolve_water_model": "`water.model` left unset resolves to `physical`, or to `paper` where the "
                                        "water gives a field only the paper's model reads or, giving no "
                                        "`depth_m`, the camera workspace or a survey reaches the default seabed "
                                        "depth; the spec records the model it resolved.",
    "DatasetSpec._camera_under_water": "With physical water, `water.depth_m`'s min lies above the top of "
                                       "`workspaces.camera` (the camera stays under water).",
    "DatasetSpec._trajectory_under_water": "With physical water and a survey, `trajectory.altitude_m` + `heave_m` "
                                           "stays below the surface.",
    "DatasetSpec._lamps_and_caustics_need_physical_light": "`lighting.lamps` and `lighting.caustics` need "
                                                           "`water.model: physical` (with water enabled).",
    "DatasetSpec._shard_work": f"`shard_size` x (width x height + the sensors' render pixels) is at most "
                               f"{MAX_SHARD_MEGAPIXELS:,.0f} megapixels.",
}

Check = Callable[..., Any]


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation but '-' and '_' dropped, spaces as '-'."""
    kept = "".join(c for c in heading.lower() if c.isalnum() or c in " -_")
    return kept.replace(" ", "-")


def _cell(text: str) -> str:
    return " ".join(text.split()).replace("|", "\\|")


def _paragraphs(doc: str | None) -> list[str]:
    """A docstring as paragraphs, each on one line."""
    if not doc:
        return []
    return [" ".join(p.split()) for p in inspect.cleandoc(doc).split("\n\n") if p.strip()]


def _own_doc(cls: type) -> str | None:
    return cls.__dict__.get("__doc__")


def _number(x: float) -> str:
    if isinstance(x, float) and not x.is_integer():
        return repr(x)
    return f"{int(x):,}" if abs(x) >= 10_000 else str(int(x))


def _bounds(items: list[Any]) -> list[str]:
    """Numeric and length bounds of annotated_types metadata, by their attribute names."""
    out = []
    for m in items:
        for attr, op in (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<")):
            if hasattr(m, attr) and type(m).__name__.lower() == attr:
                out.append(f"{op} {_number(getattr(m, attr))}")
        if type(m).__name__ == "MinLen":
            out.append(f"length >= {m.min_length}")
        if type(m).__name__ == "MaxLen":
            out.append(f"length <= {m.max_length:,}")
        if getattr(m, "pattern", None):
            out.append(f"matches `{m.pattern}`")
    return out


def _value_check(func: Check) -> str:
    """What an AfterValidator's function checks, in words."""
    name = func.__name__
    if name in VALUE_CHECKS:
        return VALUE_CHECKS[name]
    code = func.__code__
    if name == "<lambda>" and code.co_names == ("within",):
        lo, hi = [c for c in code.co_consts if isinstance(c, (int, float)) and not isinstance(c, bool)]
        return f"within [{_number(lo)}, {_number(hi)}]"
    return _documented(func, f"value validator {func.__qualname__}")


def _documented(func: Check, what: str) -> str:
    doc = _paragraphs(func.__doc__)
    if not doc:
        raise ValueError(f"{what} has no entry in seasynth.service.spec.reference and no docstring: describe it")
    return doc[0].split(". ")[0].rstrip(".")


class _Type:
    """A field's annotation read for the table: its words, its constraints and the models it holds."""

    def __init__(self, annotation: Any, metadata: list[Any]):
        self.checks: list[str] = []
        self.models: list[type[SpecModel]] = []
        self.words = self._read(annotation, metadata, "")

    def _read(self, tp: Any, metadata: list[Any], each: str) -> str:
        metadata = list(metadata)
        while get_origin(tp) is Annotated:
            tp, *extra = get_args(tp)
            metadata += extra
        for m in list(metadata):
            if isinstance(m, FieldInfo):
                metadata += m.metadata
        funcs = [m.func for m in metadata if type(m).__name__ == "AfterValidator"]
        before = {m.func.__name__ for m in metadata if type(m).__name__ == "BeforeValidator"}
        names = {f.__name__ for f in funcs}
        self.checks += [each + c for c in _bounds(metadata)]
        self.checks += [each + c for c in map(_value_check, funcs) if c]
        origin, args = get_origin(tp), get_args(tp)
        if tp is type(None):
            return "null"
        if origin in (Union, types.UnionType):
            return " or ".join(self._read(a, [], each) for a in args)
        if origin is Literal:
            self.checks.append(each + "one of " + ", ".join(f"`{a}`" for a in args))
            return "string"
        if origin is list:
            inner = self._read(args[0], [], "each ")
            return f"{inner} or list of {inner}" if "_one_class_as_list" in before else "list of " + inner
        if origin is tuple:
            inner = {self._read(a, [], "each ") for a in args}
            kind = "interval" if "ordered" in names else "vector" if "bounded" in names else "list"
            return f"{kind} of {len(args)} {inner.pop()}s" if len(inner) == 1 else f"[{', '.join(sorted(inner))}]"
        if isinstance(tp, type) and issubclass(tp, SpecModel):
            self.models.append(tp)
            return f"[{tp.__name__}](#{slug(tp.__name__)})"
        return {int: "integer", float: "number", bool: "boolean", str: "string"}[tp]


def _default(field: FieldInfo) -> str:
    if field.is_required():
        return "required"
    value = field.default_factory() if field.default_factory is not None else field.default
    if isinstance(value, BaseModel):
        try:
            if value == type(value)():
                return "its defaults"
        except ValueError:  # a model with required fields
            pass
        value = value.model_dump(mode="json")
    elif isinstance(value, list) and len(value) == 1 and isinstance(value[0], BaseModel) and \
            not value[0].model_dump(exclude_defaults=True):
        return "one at its defaults"
    elif isinstance(value, (list, tuple)):
        value = [v.model_dump(mode="json", exclude_defaults=True) if isinstance(v, BaseModel) else v for v in value]
    return f"`{json.dumps(value)}`"


def _field_comments(cls: type) -> dict[str, str]:
    """The comments written beside each field in the class body: full lines right above it, and at its lines' ends."""
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    comments: dict[int, tuple[str, bool]] = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            comments[tok.start[0]] = (tok.string.lstrip("#").strip(), tok.line.lstrip().startswith("#"))
    out = {}
    for node in ast.parse(source).body[0].body:
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        above, line = [], node.lineno - 1
        while line in comments and comments[line][1]:
            above.insert(0, comments[line][0])
            line -= 1
        lines = range(node.lineno, node.end_lineno + 1)
        inline = [comments[n][0] for n in lines if n in comments and not comments[n][1]]
        if above or inline:
            out[node.target.id] = " ".join(above + inline)
    return out


def _defined_in(cls: type, name: str) -> type:
    return next(c for c in cls.__mro__ if name in c.__dict__.get("__annotations__", {}))


def _description(cls: type[SpecModel], name: str, field: FieldInfo, read: _Type) -> str:
    if field.description:
        return field.description
    comment = _field_comments(_defined_in(cls, name)).get(name)
    if comment:
        return comment
    docs = [_paragraphs(_own_doc(m)) for m in read.models]
    return docs[0][0].split(". ")[0].rstrip(".") + "." if len(docs) == 1 and docs[0] else ""


def _validators(cls: type[SpecModel], kind: str) -> Iterator[tuple[str, Any]]:
    for dec in getattr(cls.__pydantic_decorators__, kind).values():
        yield getattr(dec.func, "__func__", dec.func).__qualname__, dec


def models_in_order() -> dict[type[SpecModel], list[str]]:
    """Every model of the spec, depth first in field order, with the dotted paths it is found at."""
    found: dict[type[SpecModel], list[str]] = {}

    def visit(cls: type[SpecModel], path: str) -> None:
        found.setdefault(cls, []).append(path)
        for name, field in cls.model_fields.items():
            read = _Type(field.annotation, field.metadata)
            sub = f"{path}.{name}" if path else name
            if get_origin(field.annotation) is list:
                sub += "[]"
            for model in read.models:
                visit(model, sub)

    visit(DatasetSpec, "")
    return found


def _preamble() -> list[str]:
    config = SpecModel.model_config
    rules = ["Ranges are intervals `[min, max]` with min <= max."]
    rules.append(f"Every interval and vector lies within +-{MAX_MAGNITUDE:,.0f}.")
    if config.get("extra") == "forbid":
        rules.append("Unknown fields are refused.")
    if config.get("allow_inf_nan") is False:
        rules.append("Numbers must be finite.")
    rules.append("Integers, numbers and booleans are strict: `true` and `\"7\"` are not integers, `1` and `\"yes\"` "
                 "are not booleans (an integer is a number).")
    return [
        "# Spec reference",
        "",
        "<!-- Generated by `python -m seasynth.service.spec.reference` from the models in service/spec/: do not "
        "edit; tests/test_docs.py checks it is current. -->",
        "",
        "Every section of the dataset spec as the pydantic models in [service/spec/](../service/spec/) validate "
        "it, from the top level (`DatasetSpec`) down. [The spec guide](spec-guide.md) explains the sections with "
        "examples. " + " ".join(rules) + " A field's constraints are checked on its own; the checks under a "
        "table join several fields.",
    ]


def _section(cls: type[SpecModel], paths: list[str]) -> list[str]:
    where = ", ".join(f"`{p}`" for p in paths) if paths != [""] else "the top level of a spec file"
    lines = ["", f"## {cls.__name__}", " ".join([f"At {where}.", *_paragraphs(_own_doc(cls))])]
    lines += ["", "| field | type | default | constraints | description |", "|---|---|---|---|---|"]
    checks = {}
    for name, dec in _validators(cls, "field_validators"):
        for field_name in dec.info.fields:
            checks.setdefault(field_name, []).append(FIELD_CHECKS.get(name) or _documented(dec.func, name))
    for name, field in cls.model_fields.items():
        read = _Type(field.annotation, field.metadata)
        constraints = "; ".join(dict.fromkeys(read.checks + checks.get(name, [])))  # tuple items repeat theirs
        cells = [f"`{name}`", read.words, _default(field), constraints, _description(cls, name, field, read)]
        lines.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    across = [MODEL_CHECKS.get(name) or _documented(dec.func, name) + "."
              for name, dec in _validators(cls, "model_validators")]
    if across:
        lines += ["", "Checks across fields:", *(f"- {c}" for c in across)]
    return lines


def reference_markdown() -> str:
    """docs/spec.md: the preamble, then one section per model of the spec, depth first in field order."""
    lines = _preamble()
    for cls, paths in models_in_order().items():
        lines += _section(cls, paths)
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> int:
    text = reference_markdown()
    if not argv:
        sys.stdout.write(text)
        return 0
    if len(argv) == 2 and argv[0] == "--check":
        try:
            with open(argv[1], encoding="utf-8") as f:
                current = f.read() == text
        except OSError as err:
            print(f"{argv[1]}: cannot read ({err.strerror or err})", file=sys.stderr)
            return 1
        if not current:
            print(f"{argv[1]}: not the current spec reference; run python -m seasynth.service.spec.reference > "
                  f"{argv[1]}", file=sys.stderr)
        return 0 if current else 1
    print("usage: python -m seasynth.service.spec.reference [--check FILE]", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

"""The manifest's JSON Schema (``manifest.schema.json``, shipped with the package) and a validator of the subset it uses.

The schema file is the one definition of a valid manifest: integrators in other languages validate with it, and
the runtime validates with it here before building any record. The vehicle runtime's base install stays numpy +
onnxruntime, so this is a small validator of exactly the keywords the schema uses (listed in ``KEYWORDS``; any
other keyword in the schema is refused when the schema loads, so the two cannot drift apart silently). The dev
tests check it against the ``jsonschema`` library on generated manifests.

Semantics follow JSON Schema 2020-12 as ``jsonschema`` implements it: a bool is neither an integer nor a number,
an integral float (``8.0``) is an integer, NaN passes ``minimum``/``maximum`` (no comparison with NaN fails).
"""

from __future__ import annotations

import functools
import importlib.resources
import json
import re
from typing import Any

SCHEMA_FILE = "manifest.schema.json"
KEYWORDS = frozenset({
    "$schema", "$id", "$ref", "$defs", "title", "description", "type", "properties", "required", "items", "enum",
    "const", "anyOf", "additionalProperties", "minimum", "maximum", "exclusiveMinimum", "minItems", "maxItems", "uniqueItems", "minLength",
    "maxLength", "pattern",
})
_ANNOTATIONS = frozenset({"$schema", "$id", "title", "description", "$defs"})


class SchemaViolation(ValueError):
    """A document that does not validate; ``path`` is where (``graphs[0].file``), the message says what."""

    def __init__(self, path: str, message: str) -> None:
        super().__init__(message)
        self.path = path


@functools.lru_cache(maxsize=1)
def manifest_schema() -> dict:
    """The parsed ``manifest.schema.json`` of this package, checked to use only the keywords this module knows."""
    text = importlib.resources.files("streamdet.runtime_ort").joinpath(SCHEMA_FILE).read_text(encoding="utf-8")
    schema = json.loads(text)
    _check_keywords(schema, "#")
    return schema


def validate(doc: Any, schema: dict | None = None, what: str = "manifest") -> None:
    """Raise SchemaViolation naming the first place where ``doc`` breaks ``schema`` (default: the manifest's)."""
    root = manifest_schema() if schema is None else schema
    _validate(doc, root, root, "", what)


def _check_keywords(node: Any, where: str) -> None:
    if isinstance(node, dict):
        unknown = sorted(k for k in node if k not in KEYWORDS and not where.endswith(("/properties", "/$defs")))
        if unknown:
            raise ValueError(f"{SCHEMA_FILE} {where}: keywords {unknown} are not implemented by runtime_ort/schema.py")
        for k, v in node.items():
            _check_keywords(v, f"{where}/{k}")
    elif isinstance(node, list):
        for i, v in enumerate(node):
            _check_keywords(v, f"{where}/{i}")


def _type_ok(value: Any, name: str) -> bool:
    if name == "integer":
        return (isinstance(value, int) and not isinstance(value, bool)) or (isinstance(value, float) and value.is_integer())
    if name == "number":
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    return {
        "string": isinstance(value, str),
        "boolean": isinstance(value, bool),
        "null": value is None,
        "object": isinstance(value, dict),
        "array": isinstance(value, list),
    }[name]


def _where(path: str, what: str) -> str:
    return f"{what} field {path}" if path else what


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _fail(schema: dict, path: str, what: str, problem: str) -> SchemaViolation:
    desc = schema.get("description")
    expect = f" (expected {desc})" if desc else ""
    return SchemaViolation(path, f"{_where(path, what)}: {problem}{expect}")


def _validate(value: Any, schema: dict, root: dict, path: str, what: str) -> None:
    if "$ref" in schema:
        ref = schema["$ref"]
        if not ref.startswith("#/$defs/"):
            raise ValueError(f"{SCHEMA_FILE}: only local #/$defs/ references are supported, got {ref!r}")
        target = root["$defs"][ref[len("#/$defs/"):]]
        merged = {**target, **{k: v for k, v in schema.items() if k != "$ref"}}
        return _validate(value, merged, root, path, what)
    if "anyOf" in schema:
        errors = []
        for option in schema["anyOf"]:
            try:
                _validate(value, option, root, path, what)
                break
            except SchemaViolation as e:
                # kept without its traceback: the traceback holds this frame, whose `errors` holds it (a cycle), and a
                # finished frame keeps its callers' frames alive, StreamingDetector.__init__'s with its sessions among
                # them, until the next full garbage collection (hundreds of MB per detector closed and dropped)
                errors.append(e.with_traceback(None))
        else:
            # the most specific complaint: the option that got deepest into the value
            deepest = max(errors, key=lambda e: len(e.path))
            if deepest.path != path:
                raise deepest
            raise _fail(schema, path, what, f"{_short(value)} is not allowed")
    if "const" in schema and not _equal(value, schema["const"]):
        raise _fail(schema, path, what, f"{_short(value)} is not supported")
    if "enum" in schema and not any(_equal(value, c) for c in schema["enum"]):
        raise _fail(schema, path, what, f"{_short(value)} is not one of {schema['enum']}")
    if "type" in schema:
        types = schema["type"] if isinstance(schema["type"], list) else [schema["type"]]
        if not any(_type_ok(value, t) for t in types):
            raise _fail(schema, path, what, f"expected {' or '.join(types)}, got {type(value).__name__} {_short(value)}")
    if _type_ok(value, "number"):
        _check_number(value, schema, path, what)
    elif isinstance(value, str):
        if len(value) < schema.get("minLength", 0):
            raise _fail(schema, path, what, f"{_short(value)} is shorter than {schema['minLength']} characters")
        if "maxLength" in schema and len(value) > schema["maxLength"]:
            raise _fail(schema, path, what, f"{_short(value)} is longer than {schema['maxLength']} characters")
        if "pattern" in schema and not re.search(schema["pattern"], value):
            raise _fail(schema, path, what, f"{_short(value)} is not allowed")
    elif isinstance(value, list):
        _check_array(value, schema, root, path, what)
    elif isinstance(value, dict):
        for key in schema.get("required", ()):
            if key not in value:
                at = f" {path}" if path else ""
                raise SchemaViolation(path, f"{what}{at} is missing the field {key!r}")
        properties = schema.get("properties", {})
        for key, sub in properties.items():
            if key in value:
                _validate(value[key], sub, root, f"{path}.{key}" if path else key, what)
        extra = schema.get("additionalProperties", True)
        if extra is not True:
            for key in value:
                if key not in properties:
                    where = f"{path}.{key}" if path else str(key)
                    if extra is False:
                        raise SchemaViolation(where, f"{_where(path, what)}: field {key!r} is not allowed")
                    _validate(value[key], extra, root, where, what)


def _check_number(value: float, schema: dict, path: str, what: str) -> None:
    if "minimum" in schema and value < schema["minimum"]:
        raise _fail(schema, path, what, f"{_short(value)} is below the minimum {schema['minimum']}")
    if "maximum" in schema and value > schema["maximum"]:
        raise _fail(schema, path, what, f"{_short(value)} is above the maximum {schema['maximum']}")
    if "exclusiveMinimum" in schema and value <= schema["exclusiveMinimum"]:
        raise _fail(schema, path, what, f"{_short(value)} must be above {schema['exclusiveMinimum']}")


def _check_array(value: list, schema: dict, root: dict, path: str, what: str) -> None:
    if len(value) < schema.get("minItems", 0):
        raise _fail(schema, path, what, f"has {len(value)} items, fewer than {schema['minItems']}")
    if "maxItems" in schema and len(value) > schema["maxItems"]:
        raise _fail(schema, path, what, f"has {len(value)} items, more than {schema['maxItems']}")
    if schema.get("uniqueItems"):
        for i, a in enumerate(value):
            if any(_equal(a, b) for b in value[:i]):
                raise _fail(schema, path, what, f"item {_short(a)} is repeated")
    if "items" in schema:
        for i, item in enumerate(value):
            _validate(item, schema["items"], root, f"{path}[{i}]", what)


def _equal(a: Any, b: Any) -> bool:
    """JSON equality: 1 == 1.0, but True != 1 (JSON Schema keeps booleans apart from numbers)."""
    if isinstance(a, bool) or isinstance(b, bool):
        return isinstance(a, bool) and isinstance(b, bool) and a == b
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return a == b  # NaN equals nothing, as in jsonschema
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    return type(a) is type(b) and a == b

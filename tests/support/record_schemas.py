"""Validate planarloc's outputs against the published JSON Schemas (``docs/schema/*.schema.json``).

Every check first parses the text as *strict* JSON (no NaN/Infinity, as JavaScript's
``JSON.parse`` would), then validates it; a failure names the file and the path inside it.
"""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
from referencing import Registry, Resource

from planarloc.io.strict_json import loads_strict

SCHEMA_DIR = Path(__file__).resolve().parents[2] / "docs" / "schema"


def _registry() -> Registry:
    resources = []
    for path in sorted(SCHEMA_DIR.glob("*.schema.json")):
        doc = json.loads(path.read_text())
        resources.append((doc["$id"], Resource.from_contents(doc)))
    return Registry().with_resources(resources)


_REGISTRY = _registry()


def validator(name: str) -> jsonschema.Draft202012Validator:
    """The validator of ``docs/schema/<name>.schema.json``."""
    doc = json.loads((SCHEMA_DIR / f"{name}.schema.json").read_text())
    jsonschema.Draft202012Validator.check_schema(doc)
    return jsonschema.Draft202012Validator(doc, registry=_REGISTRY)


def check(name: str, value: object, where: str = "") -> object:
    """``value`` (a parsed document, or its text) validated against schema ``name``; the text is
    parsed strictly first. Returns the parsed document."""
    doc = loads_strict(value) if isinstance(value, (str, bytes)) else loads_strict(json.dumps(value))
    errors = sorted(validator(name).iter_errors(doc), key=lambda e: list(e.absolute_path))
    if errors:
        e = errors[0]
        raise AssertionError(
            f"{where or name}: {len(errors)} schema error(s); first at "
            f"/{'/'.join(map(str, e.absolute_path))}: {e.message[:300]}"
        )
    return doc


def check_file(name: str, path: Path) -> object:
    """The file at ``path`` parsed strictly and validated against schema ``name``."""
    return check(name, Path(path).read_text(), str(path))

"""Loads the data contracts kept as files in ``schemas/`` (installed as package data ``logpipe.schemas``).

Arrow table schemas are small JSON documents (name, version, fields with type, nullability and a doc
string) so that they read well in review; MCAP channel schemas are JSON Schema documents used verbatim
as the channels' ``jsonschema`` encoding.
"""

from __future__ import annotations

import json
from functools import cache
from importlib import resources
from typing import Any

import pyarrow as pa

from logpipe.errors import DatasetError

_ARROW_TYPES: dict[str, pa.DataType] = {
    "string": pa.string(),
    "int64": pa.int64(),
    "int32": pa.int32(),
    "int16": pa.int16(),
    "int8": pa.int8(),
    "float64": pa.float64(),
    "float32": pa.float32(),
    "bool": pa.bool_(),
    "binary": pa.binary(),
    "list<string>": pa.list_(pa.string()),
    "list<float64>": pa.list_(pa.float64()),
    "list<int32>": pa.list_(pa.int32()),
}


def read_schema_file(filename: str) -> dict[str, Any]:
    """The parsed JSON of ``schemas/<filename>``."""
    text = resources.files("logpipe.schemas").joinpath(filename).read_text(encoding="utf-8")
    data: dict[str, Any] = json.loads(text)
    return data


def _arrow_type(name: str) -> pa.DataType:
    if name not in _ARROW_TYPES:
        raise DatasetError(f"schema type {name!r} is not one logpipe knows: {sorted(_ARROW_TYPES)}")
    return _ARROW_TYPES[name]


@cache
def arrow_schema(name: str) -> pa.Schema:
    """The Arrow schema ``schemas/<name>.json`` describes, with its name and version as schema metadata."""
    doc = read_schema_file(f"{name}.json")
    fields = [
        pa.field(f["name"], _arrow_type(f["type"]), nullable=bool(f["nullable"]), metadata={"doc": f["doc"]})
        for f in doc["fields"]
    ]
    return pa.schema(fields, metadata={"logpipe.schema": doc["name"], "logpipe.schema_version": doc["version"]})


def schema_version(name: str) -> str:
    """Version string of ``schemas/<name>.json``."""
    return str(read_schema_file(f"{name}.json")["version"])


def tracks_schema() -> pa.Schema:
    """Schema of the canonical track table."""
    return arrow_schema("tracks")


def conform(table: pa.Table, schema: pa.Schema, *, keep_dictionaries: bool = False) -> pa.Table:
    """``table`` with exactly ``schema``'s columns, order and types; missing nullable columns become nulls.

    ``keep_dictionaries``: a dictionary-encoded column whose values have the schema's type stays encoded
    (``write_parquet`` stores it as that type; a reader sees the schema's type).

    Raises:
        DatasetError: a non-nullable column is missing, or a column holds nulls it may not hold.
    """
    columns = []
    for f in schema:
        if f.name in table.column_names:
            col = table.column(f.name)
            encoded = keep_dictionaries and pa.types.is_dictionary(col.type) and col.type.value_type == f.type
            if col.type != f.type and not encoded:
                col = col.cast(f.type)
            if not f.nullable and col.null_count:
                raise DatasetError(f"column {f.name!r} has {col.null_count} nulls but may hold none")
            columns.append(col)
        elif f.nullable:
            columns.append(pa.nulls(table.num_rows, f.type))
        else:
            raise DatasetError(f"column {f.name!r} is required by schema {schema.metadata!r} but missing")
    fields = [f.with_type(c.type) if pa.types.is_dictionary(c.type) else f
              for f, c in zip(schema, columns, strict=True)]
    return pa.Table.from_arrays(columns, schema=pa.schema(fields, metadata=schema.metadata))


def json_schema(name: str) -> dict[str, Any]:
    """A JSON Schema document ``schemas/<name>.schema.json`` (MCAP channel encodings)."""
    return read_schema_file(f"{name}.schema.json")

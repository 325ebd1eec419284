"""Loads the data contracts kept as files in ``schemas/`` (installed as package data ``logpipe.schemas``).

Arrow table schemas are small JSON documents (name, version, fields with type, nullability and a doc
string) so that they read well in review; MCAP channel schemas are JSON Schema documents used verbatim
as the channels' ``jsonschema`` encoding.
"""

from __future__ import annotations

import json
import re
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
    # Ids and labels repeated over many rows: engines that read the stored Arrow schema (pyarrow, Polars) get
    # codes plus one copy of each distinct value; Parquet stores them dictionary-encoded either way.
    "dictionary<int32,string>": pa.dictionary(pa.int32(), pa.string()),
}

_FIXED_SIZE_LIST = re.compile(r"fixed_size_list<(?P<item>[a-z0-9]+)>\[(?P<size>[a-z_0-9]+)\]")
"""``fixed_size_list<ITEM>[SIZE]``: SIZE a number or a parameter of the table (``pred_len``) that the caller of
``arrow_schema`` gives."""


def read_schema_file(filename: str) -> dict[str, Any]:
    """The parsed JSON of ``schemas/<filename>``."""
    text = resources.files("logpipe.schemas").joinpath(filename).read_text(encoding="utf-8")
    data: dict[str, Any] = json.loads(text)
    return data


def _arrow_type(name: str, sizes: dict[str, int]) -> pa.DataType:
    if name in _ARROW_TYPES:
        return _ARROW_TYPES[name]
    fixed = _FIXED_SIZE_LIST.fullmatch(name)
    if fixed is None or fixed["item"] not in _ARROW_TYPES:
        raise DatasetError(f"schema type {name!r} is not one logpipe knows: {sorted(_ARROW_TYPES)} or "
                           "fixed_size_list<TYPE>[SIZE]")
    size = fixed["size"]
    if not size.isdigit() and size not in sizes:
        raise DatasetError(f"schema type {name!r} needs {size}= (a table parameter, e.g. from its metadata)")
    length = int(size) if size.isdigit() else sizes[size]
    if length < 1:
        raise DatasetError(f"schema type {name!r}: {size}={length}, expected >= 1")
    return pa.list_(_ARROW_TYPES[fixed["item"]], length)


@cache
def arrow_schema(name: str, **sizes: int) -> pa.Schema:
    """The Arrow schema ``schemas/<name>.json`` describes, with its name and version as schema metadata.

    ``sizes``: the table's parameters its fixed-size list types name (``pred_len=12`` for the predictions).

    Raises:
        DatasetError: an unknown type, or a parameter the schema needs and ``sizes`` lacks.
    """
    doc = read_schema_file(f"{name}.json")
    fields = [
        pa.field(f["name"], _arrow_type(f["type"], sizes), nullable=bool(f["nullable"]), metadata={"doc": f["doc"]})
        for f in doc["fields"]
    ]
    return pa.schema(fields, metadata={"logpipe.schema": doc["name"], "logpipe.schema_version": doc["version"]})


def optional_fields(name: str, **sizes: int) -> list[pa.Field]:
    """The ``optional_fields`` of ``schemas/<name>.json`` (columns some tables add after the contract's), as Arrow
    fields; [] when it lists none."""
    doc = read_schema_file(f"{name}.json")
    return [pa.field(f["name"], _arrow_type(f["type"], sizes), nullable=bool(f["nullable"]), metadata={"doc": f["doc"]})
            for f in doc.get("optional_fields", [])]


def field_names(name: str) -> list[str]:
    """Column names of ``schemas/<name>.json`` in order (no parameters needed)."""
    return [str(f["name"]) for f in read_schema_file(f"{name}.json")["fields"]]


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


def decode_dictionaries(table: pa.Table) -> pa.Table:
    """``table`` with every dictionary-encoded column as its value type (field metadata kept).

    For code that compares, sorts or joins columns with Arrow kernels that refuse dictionaries (``is_in``
    with a dictionary value set, ``sort_by``) or numbers values by first appearance (``dictionary_encode``).
    """
    if not any(pa.types.is_dictionary(f.type) for f in table.schema):
        return table
    schema = value_schema(table.schema)
    columns = [c.cast(f.type) if c.type != f.type else c for f, c in zip(schema, table.columns, strict=True)]
    return pa.Table.from_arrays(columns, schema=schema)


def value_schema(schema: pa.Schema) -> pa.Schema:
    """``schema`` with each dictionary type replaced by its value type."""
    return pa.schema([f.with_type(f.type.value_type) if pa.types.is_dictionary(f.type) else f for f in schema],
                     metadata=schema.metadata)


def encode_dictionaries(table: pa.Table, schema: pa.Schema) -> pa.Table:
    """``table`` (value-typed or encoded in any way) in ``schema``, each dictionary column with one dictionary in
    first-appearance order: the written file then depends on the values only, not on how they were chunked or
    encoded before (an appended ingest writes what a whole one does).

    Raises:
        DatasetError: as ``conform``.
    """
    plain = conform(decode_dictionaries(table), value_schema(schema)).combine_chunks()
    return conform(plain, schema)


def json_schema(name: str) -> dict[str, Any]:
    """A JSON Schema document ``schemas/<name>.schema.json`` (MCAP channel encodings)."""
    return read_schema_file(f"{name}.schema.json")

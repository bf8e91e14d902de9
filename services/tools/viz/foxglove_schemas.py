"""The JSON Schemas of Foxglove's message types (foxglove.PointCloud, foxglove.SceneUpdate, ...),
converted from the schemas foxglove-sdk itself carries.

The SDK's Python package gives each message class a schema (`PointCloud.get_schema()`) only as
protobuf: a FileDescriptorSet of the type and everything it uses. It ships no JSON Schema. The
export still writes JSON rather than protobuf messages: the whole file is then one encoding
(Falconry's own types have only a JSON view, services/tools/recorder/json_view.py), which Foxglove
decodes natively, any JSON Schema validator checks and any tool reads without the descriptors.
So Google's protobuf library parses the descriptors and they are converted with the mapping
Foxglove's own schema generator uses for its JSON Schemas: float64 → number, uint32 → integer ≥ 0,
bytes → base64 string, enum → oneOf of its constant values, time/duration → {sec, nsec},
repeated → array, a nested message → a nested object. No schema of a Foxglove type is written by
hand, and a field the SDK adds reaches the export with the SDK.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field

from google.protobuf.descriptor_pb2 import (DescriptorProto, EnumDescriptorProto, FieldDescriptorProto,
                                            FileDescriptorSet)
from google.protobuf.message import DecodeError

Field = FieldDescriptorProto
_NUMBER = {"type": "number"}
_INTEGER = {"type": "integer"}
_UNSIGNED = {"type": "integer", "minimum": 0}
SCALAR_SCHEMAS: dict[int, dict] = {
    Field.TYPE_DOUBLE: _NUMBER, Field.TYPE_FLOAT: _NUMBER,
    Field.TYPE_INT32: _INTEGER, Field.TYPE_INT64: _INTEGER, Field.TYPE_SINT32: _INTEGER,
    Field.TYPE_SINT64: _INTEGER, Field.TYPE_SFIXED32: _INTEGER, Field.TYPE_SFIXED64: _INTEGER,
    Field.TYPE_UINT32: _UNSIGNED, Field.TYPE_UINT64: _UNSIGNED, Field.TYPE_FIXED32: _UNSIGNED,
    Field.TYPE_FIXED64: _UNSIGNED,
    Field.TYPE_BOOL: {"type": "boolean"},
    Field.TYPE_STRING: {"type": "string"},
    Field.TYPE_BYTES: {"type": "string", "contentEncoding": "base64"},
}
# Foxglove's JSON form of protobuf's well-known time types: {sec, nsec}, not RFC 3339 strings
WELL_KNOWN = {
    ".google.protobuf.Timestamp": {
        "type": "object", "title": "time",
        "properties": {"sec": {"type": "integer", "minimum": 0},
                       "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}},
    },
    ".google.protobuf.Duration": {
        "type": "object", "title": "duration",
        "properties": {"sec": {"type": "integer"},
                       "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}},
    },
}


class DescriptorError(ValueError):
    """The SDK's schema is not a protobuf FileDescriptorSet holding the type and all it uses."""


@dataclass
class Descriptors:
    """Every message and enum of a FileDescriptorSet, by full name (".foxglove.PointCloud"), the
    form of a field's type_name."""

    messages: dict[str, DescriptorProto] = field(default_factory=dict)
    enums: dict[str, EnumDescriptorProto] = field(default_factory=dict)

    @classmethod
    def parse(cls, file_descriptor_set: bytes) -> Descriptors:
        try:
            files = FileDescriptorSet.FromString(file_descriptor_set)
        except DecodeError as error:
            raise DescriptorError(f"not a protobuf FileDescriptorSet: {error}") from None
        found = cls()
        for file in files.file:
            found._add(f".{file.package}" if file.package else "", file.message_type, file.enum_type)
        return found

    def _add(self, scope: str, messages, enums) -> None:
        for enum in enums:
            self.enums[f"{scope}.{enum.name}"] = enum
        for message in messages:
            full_name = f"{scope}.{message.name}"
            self.messages[full_name] = message
            self._add(full_name, message.nested_type, message.enum_type)


def json_schema_of(message_class) -> dict:
    """The JSON Schema of a foxglove-sdk message class (e.g. foxglove.messages.PointCloud), with
    the class's schema name as title."""
    schema = message_class.get_schema()
    if schema.encoding != "protobuf":
        raise DescriptorError(f"{schema.name}: expected a protobuf schema from foxglove-sdk, got {schema.encoding!r}")
    try:
        descriptors = Descriptors.parse(bytes(schema.data))
    except DescriptorError as error:
        raise DescriptorError(f"{schema.name}: {error}") from None
    if f".{schema.name}" not in descriptors.messages:
        raise DescriptorError(f"{schema.name} is not in the schema foxglove-sdk gives for it")
    return {"$comment": "converted from foxglove-sdk's protobuf schema (services/tools/viz/foxglove_schemas.py)",
            **_message_schema(descriptors, f".{schema.name}")}


def _message_schema(descriptors: Descriptors, full_name: str) -> dict:
    properties = {}
    for proto_field in descriptors.messages[full_name].field:
        item = _field_schema(descriptors, proto_field)
        repeated = proto_field.label == Field.LABEL_REPEATED
        properties[proto_field.name] = {"type": "array", "items": item} if repeated else item
    return {"title": full_name.lstrip("."), "type": "object", "properties": properties}


def _field_schema(descriptors: Descriptors, proto_field: FieldDescriptorProto) -> dict:
    name, type_name = proto_field.name, proto_field.type_name
    if proto_field.type == Field.TYPE_MESSAGE:
        if type_name in WELL_KNOWN:
            return copy.deepcopy(WELL_KNOWN[type_name])
        if type_name not in descriptors.messages:
            raise DescriptorError(f"field {name}: message {type_name} is not in the schema")
        return _message_schema(descriptors, type_name)
    if proto_field.type == Field.TYPE_ENUM:
        enum = descriptors.enums.get(type_name)
        if enum is None:
            raise DescriptorError(f"field {name}: enum {type_name} is not in the schema")
        return {"title": type_name.lstrip("."),
                "oneOf": [{"title": value.name, "const": value.number} for value in enum.value]}
    if proto_field.type not in SCALAR_SCHEMAS:
        type_label = Field.Type.Name(proto_field.type)
        raise DescriptorError(f"field {name}: protobuf type {type_label} has no JSON form here")
    return dict(SCALAR_SCHEMAS[proto_field.type])

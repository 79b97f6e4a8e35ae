"""Compiled mirrors of the wire models: msgspec structs generated from the pydantic schemas.

The pydantic models in :mod:`agos.runtime.schemas` are the contract and stay the only place a
message is defined. :func:`mirror` derives from a model a ``msgspec.Struct`` class with the same
name, fields (in the same order), types and defaults, nested models mirrored in turn. msgspec reads
msgpack straight into such structs and checks every type while it reads, in C: for an observation
that is several times cheaper than unpacking into Python objects and validating them with pydantic,
which is what the decision round trip pays on each side (docs/ARCHITECTURE.md §6).

A mirror reads like its model (``obs.pose.position_world_m``, ``obs.coordination.candidates[0]``,
tuples, lists, dicts), so a policy written against the models works on either. What a mirror does
not have is the model's methods (``model_dump``, ``model_copy``...): use :func:`to_model` for those.
One deliberate difference: a ``bytes`` field (the encoded images) is a read-only ``memoryview``
in a mirror, so decoding does not copy the image bytes out of the received payload (a quarter of a
megabyte per UAV observation). It works wherever bytes-like input is taken (``len``, slicing,
``==``, ``np.frombuffer``, ``cv2``, ``base64``, ``hashlib``); ``bytes(view)`` copies it when a
``bytes`` method or pickling is needed. A view keeps the payload it points into alive.
A mirror accepts a subset of what its model accepts (no lax coercion such as ``"3"`` for an
``int``), so anything it refuses goes back to pydantic, which accepts or names the bad field.
"""

from __future__ import annotations

import sys
import types
import typing
from typing import Any

import msgspec
from pydantic import BaseModel
from pydantic_core import PydanticUndefined

_MIRRORS: dict[type[BaseModel], type[msgspec.Struct]] = {}
_TAGGED: dict[tuple[type[BaseModel], tuple[str, ...]], type[msgspec.Struct]] = {}
_MODELS: dict[type[msgspec.Struct], type[BaseModel]] = {}
_PLAIN_CONFIG = {"extra", "frozen", "title", "use_attribute_docstrings"}
"""``model_config`` keys that do not change what a model accepts or the values it keeps (a
mirror forbids unknown fields whatever ``extra`` says: it may be stricter, never more lenient)."""


def mirror(model: type[BaseModel]) -> type[msgspec.Struct]:
    """The struct class mirroring ``model`` (made once, then cached); see :func:`mirror_fields`."""
    found = _MIRRORS.get(model)
    if found is not None:
        return found
    found = msgspec.defstruct(model.__name__, mirror_fields(model), kw_only=True, forbid_unknown_fields=True,
                              module=__name__, namespace={"__reduce__": _reduce})
    _MIRRORS[model], _MODELS[found] = found, model
    module = sys.modules[__name__]
    if not hasattr(module, model.__name__):  # pickle finds a class by module and name
        setattr(module, model.__name__, found)
    return found


def tagged(model: type[BaseModel], raw: tuple[str, ...] = ()) -> type[msgspec.Struct]:
    """What a receiver reads a whole message into: ``mirror(model)`` with its ``type`` field required
    (a wire message's ``type`` is how :func:`agos.runtime.codec.decode` tells messages apart, and
    pydantic's union requires it, whereas the model defaults it) and the fields named in ``raw``
    read as ``msgspec.Raw`` (their msgpack left as it is, ``UNSET`` when absent), for the reader to
    replace in place with their values. A subclass of the mirror: ``isinstance`` holds, the same
    fields in the same order write the same bytes; pickled and deep-copied as the mirror itself."""
    found = _TAGGED.get((model, raw))
    if found is None:
        base = mirror(model)
        fields: list[tuple[Any, ...]] = [("type", model.model_fields["type"].annotation)]
        for name in raw:
            required = model.model_fields[name].is_required()
            fields.append((name, msgspec.Raw) if required else (name, msgspec.Raw, msgspec.UNSET))
        found = msgspec.defstruct(model.__name__, fields, bases=(base,), kw_only=True, forbid_unknown_fields=True,
                                  module=__name__)
        _TAGGED[(model, raw)], _MODELS[found] = found, model
    return found


def _reduce(struct: msgspec.Struct) -> tuple[Any, ...]:
    """Pickling (and ``copy.deepcopy``) of a mirror: its memoryviews as the bytes they show."""
    values = {}
    for name in struct.__struct_fields__:
        value = getattr(struct, name)
        values[name] = bytes(value) if isinstance(value, memoryview) else value
    return _rebuild, (_MIRRORS[_MODELS[type(struct)]], values)


def _rebuild(kind: type[msgspec.Struct], values: dict[str, Any]) -> msgspec.Struct:
    return kind(**values)


def mirror_fields(model: type[BaseModel]) -> list[tuple[Any, ...]]:
    """``model``'s fields as ``msgspec.defstruct`` takes them: ``(name, type)`` when required, else
    ``(name, type, default)``; nested models replaced by their mirrors.

    Raises ``TypeError`` for a model a struct cannot mirror exactly: field constraints (``ge``,
    patterns...), aliases, validators or serializers, or config that changes what is accepted
    (``str_strip_whitespace``, ``strict``...): checks and conversions msgspec would not make."""
    decorators = model.__pydantic_decorators__
    if decorators.field_validators or decorators.model_validators or decorators.field_serializers or \
            decorators.model_serializers:
        raise TypeError(f"{model.__name__} has validators or serializers; a struct cannot mirror it")
    if set(model.model_config) - _PLAIN_CONFIG:
        raise TypeError(f"{model.__name__} sets {sorted(set(model.model_config) - _PLAIN_CONFIG)}; a struct cannot mirror it")
    fields: list[tuple[Any, ...]] = []
    for name, field in model.model_fields.items():
        if field.metadata:
            raise TypeError(f"{model.__name__}.{name} has constraints {field.metadata}; a struct cannot mirror it")
        if field.alias or field.validation_alias or field.serialization_alias or field.exclude:
            raise TypeError(f"{model.__name__}.{name} has an alias or is excluded; a struct cannot mirror it")
        kind = _mirror_type(field.annotation)
        if field.default_factory is not None:
            fields.append((name, kind, msgspec.field(default_factory=field.default_factory)))
        elif field.default is PydanticUndefined:
            fields.append((name, kind))
        else:
            fields.append((name, kind, field.default))
    return fields


def to_model(value: Any) -> Any:
    """The pydantic model of a mirror struct (validated again; other values returned as they are).
    The struct's values pass through msgpack, which turns its memoryviews back into ``bytes``
    (pydantic takes no memoryview) and any pydantic part into its fields."""
    model = _MODELS.get(type(value))
    if model is None:
        return value
    return model.model_validate(msgspec.msgpack.decode(msgspec.msgpack.encode(value, enc_hook=_dump)))


def _dump(value: Any) -> Any:
    if isinstance(value, BaseModel):  # a model stored in a mirror (a policy may set one)
        return value.model_dump()
    raise TypeError(f"cannot convert a {type(value).__name__} to its model")


def _mirror_type(annotation: Any) -> Any:
    """A field's type with every pydantic model in it replaced by its mirror, and ``bytes`` by
    ``memoryview`` (read without a copy; see the module's docstring)."""
    if annotation is bytes:
        return memoryview
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return mirror(annotation)
    origin = typing.get_origin(annotation)
    if origin is None or origin is typing.Literal:
        return annotation
    args = tuple(_mirror_type(arg) for arg in typing.get_args(annotation))
    if origin in (typing.Union, types.UnionType):
        return typing.Union[args]  # noqa: UP007 (built from a tuple)
    if origin is typing.Annotated:
        raise TypeError(f"annotated type {annotation} cannot be mirrored exactly")
    return origin[args]

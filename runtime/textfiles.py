"""The text files people write for agos (settings, comm profiles, episode files): one line for every way
one can be bad, never a traceback.

:func:`read_toml` turns each way a TOML file can be unreadable (not a file, no permission, not UTF-8,
not TOML, nested too deeply) into a :class:`TextFileError` whose message is the reason alone, for the
loader to prefix with what it was reading; a missing file raises ``FileNotFoundError``, which loaders
answer with their own hint. :func:`one_line` keeps a message built from a file's contents (a key with a
line break in it) on one line.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError


class TextFileError(ValueError):
    """Why a file could not be read, in a few words (no path: the loader adds its own)."""


def one_line(text: str) -> str:
    """``text`` with line breaks and other control characters escaped (``\\n``), so a message quoting
    a file's contents stays one line."""
    return "".join(ch if ch.isprintable() else repr(ch)[1:-1] for ch in text)


def read_toml(path: Path) -> dict[str, Any]:
    """The tables of the TOML file ``path``; ``FileNotFoundError`` when there is none, else
    :class:`TextFileError` for a file that cannot be read as TOML."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise TextFileError(f"cannot read it ({exc.strerror or exc})") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise TextFileError(f"not UTF-8 text (byte {exc.start})") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise TextFileError(one_line(f"not valid TOML ({exc})")) from None
    except RecursionError:
        raise TextFileError("not valid TOML (nested too deeply)") from None


ProfileT = TypeVar("ProfileT", bound=BaseModel)


def read_profile(name_or_path: str | Path, folder: Path, model: type[ProfileT], error: type[Exception], *,
                 what: str, known_as: str) -> ProfileT:
    """A profile (comm, model link, pose error) by name (``folder/<name>.toml``) or file path, its
    ``name`` defaulting to the file's stem; ``error`` (one line naming the file and the field) for a
    missing, unreadable or invalid one. ``what`` and ``known_as`` word the missing-file line."""
    path = Path(name_or_path)
    if not path.suffix:
        path = folder / f"{name_or_path}.toml"
    elif not path.exists() and path.parent == Path(".") and (folder / path.name).exists():
        path = folder / path.name
    try:
        data = read_toml(path)
    except FileNotFoundError:
        known = ", ".join(sorted(p.stem for p in folder.glob("*.toml")))
        raise error(one_line(f"{what} {name_or_path}: no such file ({path}); {known_as}: {known}")) from None
    except TextFileError as exc:
        raise error(one_line(f"{path}: {exc}")) from None
    data.setdefault("name", path.stem)
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"])
        msg = str(err["msg"]).removeprefix("Value error, ")
        raise error(one_line(f"{path}: {where + ': ' if where else ''}{msg}")) from None

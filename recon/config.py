"""Method options from a file (``lfrig reconstruct --config FILE``).

Two kinds of file hold the same thing, the flags of ``lfrig reconstruct`` by their long names with
``_`` for ``-`` (``window_sizes``, ``disparity_range``, ``method``, ``preset``):

- a **TOML** file of top-level keys::

      method = "entropy"
      preset = "paper"
      disparity_range = [-1.0, 1.5]
      window_sizes = [3, 5, 7]
      joint = false

- a **JSON** object of the same keys, or a ``result.json`` (an object with ``method`` and ``options``),
  whose options are taken as such a file, so that a result is reproduced by passing its
  ``result.json`` back.

:func:`read_config` reads the file into ``{key: value}``; it checks the file's syntax and that every
key is a method flag's, naming the closest one for a misspelt key. The values are checked by the
command line: the caller turns them into flag tokens (:func:`config_tokens`) and parses them with
the flags' own types.
"""

from __future__ import annotations

import difflib
import json
import os
import tomllib
from pathlib import Path
from typing import Any, Iterable

from recon.errors import ReconError


class ConfigError(ReconError):
    """An options file that cannot be used as it is (the message names the file and the key)."""


def read_config(path: str | os.PathLike, *, keys: Iterable[str]) -> dict[str, Any]:
    """The options in a TOML or JSON file (see the module docstring), ``{key: value}``.

    ``keys``: the valid keys (the flags' names with ``_``). A ``.json`` file is JSON, anything else TOML.

    Raises
    ------
    ConfigError
        The file is missing or not valid TOML/JSON, holds a table or a key that is not an option.
    """
    path = Path(path)
    valid = sorted(keys)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such options file") from None
    except (IsADirectoryError, UnicodeDecodeError) as error:
        raise ConfigError(f"{path}: not a text file of options ({error.__class__.__name__}); pass a .toml or .json file") from None
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as error:
            raise ConfigError(f"{path}: not valid JSON ({error}); fix it or pass a TOML file") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: a JSON options file is one object of option names and values")
        if isinstance(data.get("options"), dict) and "method" in data:  # a result.json
            data = {"method": data["method"], **data["options"]}
    else:
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as error:
            raise ConfigError(f"{path}: not valid TOML ({error})") from None
    for key, value in data.items():
        if isinstance(value, dict):
            raise ConfigError(f"{path}: [{key}] is a table; write the options as top-level keys (window_sizes = [3, 5])")
        if key not in valid:
            close = difflib.get_close_matches(key, valid, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else f"; see lfrig reconstruct --help for the options"
            raise ConfigError(f"{path}: unknown option {key!r}{hint}")
    return data


def config_tokens(options: dict[str, Any], *, path: Path) -> list[tuple[str, list[str]]]:
    """``[(key, flag tokens)]`` for each option, as it would be typed: ``--window-sizes 3 5``,
    ``--joint``/``--no-joint`` for booleans. Values of another kind than a flag takes are refused."""
    out = []
    for key, value in options.items():
        flag = "--" + key.replace("_", "-")
        if isinstance(value, bool):
            out.append((key, [flag if value else "--no-" + key.replace("_", "-")]))
        elif isinstance(value, (list, tuple)):
            if not value or any(isinstance(v, (dict, list, tuple, bool)) for v in value):
                raise ConfigError(f"{path}: option {key!r} = {value!r}: give a list of numbers")
            out.append((key, [flag, *map(_text, value)]))
        elif isinstance(value, (int, float, str)):
            out.append((key, [f"{flag}={_text(value)}"]))
        else:
            raise ConfigError(f"{path}: option {key!r} = {value!r}: give a number, a word, true/false or a list")
    return out


def _text(value: Any) -> str:
    return repr(value) if isinstance(value, float) else str(value)


__all__ = ["ConfigError", "config_tokens", "read_config"]

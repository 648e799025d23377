"""Loading scene files with ``-D key=value`` parameters, with errors that name the problem."""
import os

import mitsuba as mi


class SceneFileError(ValueError):
    """A scene file is missing or cannot be parsed."""


def parse_value(text: str):
    """``"32"`` → 32, ``"0.5"`` → 0.5, anything else stays a string (as Mitsuba's ``-D``)."""
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def parse_defines(defines) -> dict:
    """``["res=32", "spp=4"]`` → ``{"res": 32, "spp": 4}``."""
    params = {}
    for item in defines or ():
        if "=" not in item:
            raise SceneFileError(f"-D {item!r}: expected key=value")
        key, value = item.split("=", 1)
        params[key.strip()] = parse_value(value.strip())
    return params


def load_scene(path, **params) -> "mi.Scene":
    """``mi.load_file`` with a clear error for a missing file."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise SceneFileError(f"scene file not found: {path}")
    return mi.load_file(path, **params)

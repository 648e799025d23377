"""Loading scene files with ``-D key=value`` parameters, with errors that name the problem.

:func:`load_scene` is ``mi.load_file`` plus: one-line :class:`SceneFileError` messages for a
missing file, malformed XML, a parameter the scene does not use or cannot parse; and
``film_res``, which sets the film's longer side to a number of pixels (keeping the aspect ratio)
for scenes that have no ``$res`` parameter of their own.
"""
import os
import re
import tempfile
import xml.etree.ElementTree as ET

import mitsuba as mi


class SceneFileError(ValueError):
    """A scene file is missing or cannot be parsed."""


#: Mitsuba's film size when a scene gives none (hdrfilm's defaults)
DEFAULT_FILM_SIZE = (768, 576)


def scene_label(path) -> str:
    """A scene's name in tables: the file's stem (``office`` for scenes_xml/office.xml), or its
    folder's name where the stem names no scene (``veach-bidir`` for .../veach-bidir/scene.xml,
    ``tut-cbox`` for .../tut-cbox/cbox.xml)."""
    stem = os.path.splitext(os.path.basename(path))[0]
    return os.path.basename(os.path.dirname(os.path.abspath(path))) if stem in ("scene", "cbox") \
        else stem


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
        key = key.strip()
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", key):
            raise SceneFileError(f"-D {item!r}: {key!r} is not a parameter name")
        params[key] = parse_value(value.strip())
    return params


def mitsuba_error_message(exc) -> str:
    """The useful part of a Mitsuba exception, on one line.

    Drops the ``[parser.cpp:451]`` source locations and, for a Python exception raised inside
    a plugin's constructor (which Mitsuba reports with its traceback), keeps only the final
    ``Error: message`` line's message."""
    text = str(exc).strip()
    if "Traceback (most recent call last)" in text:
        last = text.splitlines()[-1].strip()
        match = re.match(r"^[A-Za-z_][\w.]*(Error|Exception|Warning)\b:\s*(.*)$", last)
        text = match.group(2) if match else last
    text = re.sub(r"\[[\w./\\-]+:\d+\]\s*", "", text)
    parts = [line.strip().lstrip("- ").strip() for line in text.splitlines()]
    return " ".join(p for p in parts if p)


def _scene_error(path, exc, shown_path=None) -> SceneFileError:
    """A :class:`SceneFileError` for Mitsuba's error ``exc`` while loading ``path``."""
    msg = mitsuba_error_message(exc)
    shown = shown_path or path
    if shown_path:
        msg = msg.replace(path, shown_path)
    unused = re.match(r"Found unused parameters:\s*(.*)$", msg)
    if unused:
        names = unused.group(1).replace("$", "")
        return SceneFileError(f"{shown}: unknown parameter(s) {names}: the scene uses no "
                              "such $name")
    if shown not in msg:
        msg = f"{shown}: {msg}"
    return SceneFileError(msg)


def _resolve(value, params: dict, defaults: dict, what: str, path):
    """A film attribute's value: a literal, or ``$name`` from ``params`` / ``<default>``."""
    if value is None:
        return None
    value = value.strip()
    if value.startswith("$"):
        name = value[1:]
        if name in params:
            value = str(params[name])
        elif name in defaults:
            value = defaults[name]
        else:
            raise SceneFileError(f"{path}: {what}={value}: no -D {name}=... and no "
                                 f"<default name=\"{name}\">")
    try:
        return int(value)
    except ValueError:
        raise SceneFileError(f"{path}: {what}={value!r}: expected an integer") from None


def _film_size_element(film, name):
    """The ``<integer name=...>`` child of ``film`` (None when absent)."""
    for child in film:
        if child.get("name") == name:
            return child
    return None


def set_film_res(root, film_res: int, params: dict, path) -> list:
    """Set every sensor's film in the parsed scene ``root`` so that its longer side is
    ``film_res`` pixels (the other side scaled to keep the aspect ratio, at least 1; a crop
    window is scaled alike). Sizes given as ``$name`` are resolved from ``params`` and the
    scene's ``<default>`` values first. Returns the new (width, height) of each film."""
    film_res = int(film_res)
    if film_res < 1:
        raise SceneFileError(f"film_res={film_res}: must be >= 1")
    defaults = {d.get("name"): d.get("value") for d in root.iter("default")}
    sizes = []
    sensors = list(root.iter("sensor"))
    if not sensors:
        raise SceneFileError(f"{path}: no <sensor>: cannot set the film size")
    for sensor in sensors:
        film = sensor.find("film")
        if film is None:
            film = ET.SubElement(sensor, "film", {"type": "hdrfilm"})
        w = _resolve(_attr(film, "width"), params, defaults, "width", path)
        h = _resolve(_attr(film, "height"), params, defaults, "height", path)
        w = DEFAULT_FILM_SIZE[0] if w is None else w
        h = DEFAULT_FILM_SIZE[1] if h is None else h
        if w < 1 or h < 1:
            raise SceneFileError(f"{path}: film size {w}x{h}: must be at least 1x1")
        scale = film_res / max(w, h)
        new = {"width": max(1, round(w * scale)), "height": max(1, round(h * scale))}
        for name in ("crop_width", "crop_height", "crop_offset_x", "crop_offset_y"):
            value = _resolve(_attr(film, name), params, defaults, name, path)
            if value is not None:
                new[name] = max(1 if name.startswith("crop_w") or name.startswith("crop_h")
                                else 0, round(value * scale))
        for name, value in new.items():
            el = _film_size_element(film, name)
            if el is None:
                el = ET.SubElement(film, "integer", {"name": name})
            el.set("value", str(value))
        sizes.append((new["width"], new["height"]))
    return sizes


def _attr(film, name):
    el = _film_size_element(film, name)
    return None if el is None else el.get("value")


def load_scene(path, film_res=None, **params) -> "mi.Scene":
    """``mi.load_file(path, **params)`` with clear errors (:class:`SceneFileError`, one line,
    naming the file) and an optional ``film_res``.

    ``film_res``: the film's longer side in pixels, the aspect ratio kept (see
    :func:`set_film_res`). The XML is parsed with ElementTree, its film size rewritten, and the
    copy written to a temporary folder and loaded with the scene's own folder first on
    Mitsuba's file resolver, so relative mesh / texture paths resolve as before; nothing is
    written beside the scene. A parameter only the film size used is dropped, not reported as
    unused."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise SceneFileError(f"scene file not found: {path}")
    if film_res is None:
        try:
            return mi.load_file(path, **params)
        except RuntimeError as e:
            raise _scene_error(path, e) from e
    with open(path, "rb") as f:
        original = f.read()
    try:
        root = ET.fromstring(original)
    except ET.ParseError as e:
        raise SceneFileError(f"{path}: malformed XML: {e}") from e
    set_film_res(root, film_res, params, path)
    text = ET.tostring(root, encoding="unicode")
    kept = {}
    for key, value in params.items():
        pattern = r"\$" + re.escape(key) + r"(?![A-Za-z0-9_])"
        if re.search(pattern.encode(), original) and not re.search(pattern, text):
            continue  # only the film size used it
        kept[key] = value
    folder = os.path.dirname(os.path.abspath(path))
    resolver = mi.file_resolver()
    saved = [resolver[i] for i in range(len(resolver))]
    with tempfile.TemporaryDirectory(prefix="mi_twopass_scene_") as tmp:
        copy = os.path.join(tmp, os.path.basename(path))
        with open(copy, "w", encoding="utf-8") as f:
            f.write(text)
        resolver.prepend(folder)
        try:
            return mi.load_file(copy, **kept)
        except RuntimeError as e:
            raise _scene_error(copy, e, shown_path=path) from e
        finally:
            resolver.clear()
            for entry in saved:
                resolver.append(entry)

"""The self-contained HTML page: the template, style and renderer shipped beside this module, with the scene's
data inlined as JSON (arrays as base64). The page fetches nothing (its Content-Security-Policy forbids it)."""

from __future__ import annotations

import html
import json
import re
from importlib import resources

_PLACEHOLDER = re.compile(r"\$(TITLE|STYLE|SCENE|SCRIPT)\b")


def _asset(name: str) -> str:
    return resources.files("mapsqueeze.view").joinpath(name).read_text(encoding="utf-8")


def render_page(scene: dict) -> str:
    """The page's HTML text for a `build_scene` dict."""
    values = {
        "TITLE": html.escape(scene["name"]),
        "STYLE": _asset("viewer.css"),
        # "</" inside JSON would end the script element early; "<\/" reads back as the same string
        "SCENE": json.dumps(scene, separators=(",", ":"), allow_nan=False).replace("</", "<\\/"),
        "SCRIPT": _asset("viewer.js"),
    }
    return _PLACEHOLDER.sub(lambda match: values[match.group(1)], _asset("template.html"))

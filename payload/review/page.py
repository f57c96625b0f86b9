"""The review's web page: meshcat's viewer, the scene's commands, and the overlay.

One page serves every way of showing a review: :func:`static_html` embeds the scene's
commands (each a msgpack blob, base64) and its :class:`~payload.review.scene.Overlay`,
so the file stands alone; :func:`live_html` embeds nothing and fetches ``update`` from
the server that sent it (:mod:`payload.review.live`). The overlay (``overlay.js``)
draws the title, the colour legend, the labels (placed each frame by a layout pass so
no two overlap, with leader lines to what they name), the trial phase, an error banner
and, for trial replays, the chase camera; it draws the 3-D view in the part of the page
below the title (with its verdict and banner) and the phase, the camera's frame scaled
into it, and a design review's bays and stowed payload (the overlay's ``subject``) clear
of the legend too.
"""

from __future__ import annotations

import base64
import hashlib
import html
import json
import re
from functools import cache
from pathlib import Path
from typing import Any

from payload.envelope.drawing import FAIL_COLOUR, PASS_COLOUR
from payload.review.scene import FAIL, PASS, Scene, tab_title

OVERLAY_JS = Path(__file__).with_name("overlay.js")

VERDICT_FONT_PX = 18
"""The verdict line's size [px]: the first thing a reviewer reads, larger than the title
(16 px) and the body text (13 px), bold, in its outcome's colour."""

STYLE = """
body { margin: 0; }
#meshcat-pane { width: 100vw; height: 100vh; overflow: hidden; position: relative; }
#payload-overlay { position: absolute; inset: 0; pointer-events: none;
  font: 13px/1.3 sans-serif; color: #111; }
#payload-leaders { position: absolute; inset: 0; width: 100%; height: 100%; }
#payload-leaders line { stroke: #222; stroke-width: 1; }
#payload-head { position: absolute; left: 10px; top: 8px; right: 270px;
  display: flex; flex-direction: column; align-items: flex-start; gap: 4px; }
#payload-title { font-size: 16px; font-weight: 600;
  background: rgba(255,255,255,0.85); padding: 2px 6px; max-width: calc(100% - 12px); }
.payload-subtitle { font-size: 12px; font-weight: 400; color: #333; }
#payload-overlay.payload-has-phase #payload-head { right: 370px; }
#payload-legend { position: absolute; left: 10px; bottom: 10px; font-size: 12px;
  background: rgba(255,255,255,0.85); padding: 4px 6px; border: 1px solid #ccc; }
.payload-legend-row { display: flex; align-items: center; gap: 6px; }
.payload-swatch { width: 12px; height: 12px; border: 1px solid #555; flex: none; }
.payload-label { position: absolute; white-space: nowrap; font-size: 12px;
  background: rgba(255,255,255,0.9); border: 1px solid #555; padding: 0 4px; }
#payload-phase { position: absolute; right: 10px; top: 32px;
  font-size: 20px; font-weight: 600; background: rgba(255,255,255,0.85); padding: 2px 8px;
  display: none; }
#payload-error { align-self: stretch; display: none;
  background: #b00020; color: white; padding: 4px 8px; font-size: 14px; }
""" + (
    f".payload-verdict {{ font-size: {VERDICT_FONT_PX}px; font-weight: 700; color: #111; }}\n"
    f".payload-verdict-{PASS} {{ color: {PASS_COLOUR}; }}\n"
    f".payload-verdict-{FAIL} {{ color: {FAIL_COLOUR}; }}\n"
)
"""The page's style: the overlay's boxes, and the verdict styled by its outcome (its
colours the envelope report's pass and fail colours)."""

_UUID = re.compile(rb"[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}")


@cache
def _meshcat_js() -> str:
    from meshcat.servers.zmqserver import VIEWER_ROOT

    return (Path(VIEWER_ROOT) / "main.min.js").read_text(encoding="utf-8")


def _ext(obj: Any) -> Any:
    import msgpack
    import umsgpack

    if isinstance(obj, umsgpack.Ext):  # meshcat's typed arrays
        return msgpack.ExtType(obj.type, obj.data)
    raise TypeError(f"cannot pack {type(obj).__name__}")


def packed(command: Any) -> bytes:
    """One meshcat command as the msgpack blob the viewer decodes (meshcat's own encoder,
    umsgpack, is pure Python; msgpack's C packer writes the same message much faster)."""
    import msgpack

    return msgpack.packb(command.lower(), default=_ext, use_bin_type=True)


def command_key(command: Any, blob: bytes) -> tuple[str, str, bytes]:
    """What a command sets and its content, for telling what changed between two builds.

    meshcat gives every geometry, material and texture a fresh random UUID, so two builds
    of the same scene differ only there; the content compares with the UUIDs blanked.

    Returns:
        ``(type, path, content digest)``; for ``set_property`` the type names the property.
    """
    low = command.lower()
    kind = low["type"] + (f":{low['property']}" if low["type"] == "set_property" else "")
    return kind, low.get("path", ""), hashlib.sha1(_UUID.sub(b"", blob)).digest()


def scene_blobs(scene: Scene) -> list[bytes]:
    """Every command of the scene (viewer settings and animation included), packed."""
    return [packed(c) for c in scene.all_commands()]


def page_html(data: dict[str, Any] | None) -> str:
    """The page, with ``data`` (``commands``, ``overlay``, ``error``) embedded or, with
    ``None``, fetching it from the server that sent the page."""
    embedded, title = "", ""
    if data is not None:
        text = json.dumps(data, separators=(",", ":")).replace("</", "<\\/")
        embedded = f'<script id="payload-data" type="application/json">{text}</script>'
        title = (data.get("overlay") or {}).get("title", "")
    return f"""<!DOCTYPE html>
<html>
<head><meta charset="utf-8"><title>{html.escape(tab_title(title))}</title>
<link rel="icon" href="data:,">
<style>{STYLE}</style></head>
<body>
<div id="meshcat-pane"></div>
<script>{_meshcat_js()}</script>
<script>var viewer = new MeshCat.Viewer(document.getElementById("meshcat-pane"));</script>
{embedded}
<script>{OVERLAY_JS.read_text(encoding="utf-8")}</script>
</body>
</html>
"""


def static_html(scene: Scene) -> str:
    """The scene, its animation and overlay as one standalone HTML page."""
    blobs = [base64.b64encode(b).decode("ascii") for b in scene_blobs(scene)]
    data = {"commands": blobs, "overlay": scene.overlay.as_json(), "error": None}
    return page_html(data)


def live_html() -> str:
    """The page a live review serves: it fetches the scene and its changes."""
    return page_html(None)


__all__ = [
    "OVERLAY_JS",
    "STYLE",
    "VERDICT_FONT_PX",
    "command_key",
    "live_html",
    "packed",
    "page_html",
    "scene_blobs",
    "static_html",
]

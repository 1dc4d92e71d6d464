"""The lens of a frame: a perspective field of view or an orthographic view height, chosen from
what a request names and the scene's default camera. Shared by ``visnerf render``, ``animate``,
movie paths and the server, so they frame a scene alike."""

import math
from collections.abc import Mapping
from typing import Literal

Projection = Literal["perspective", "orthographic"]

DEFAULT_FOV_DEG = 30.0
"""The field of view of a scene whose default camera names no lens (the client's too)."""


def choose_lens(
    camera: Mapping[str, float],
    fov_deg: float | None = None,
    view_height: float | None = None,
    projection: Projection | None = None,
) -> tuple[float | None, float | None]:
    """(fov_deg, view_height) of a frame, exactly one of them None.

    The projection is the one asked for, else the one a given lens implies, else the scene's own
    (orthographic where its default camera has a ``view_height``). A lens the request leaves out is
    the scene's, or the one that frames the orbit centre alike from the default distance
    (``view_height = 2 d tan(fov / 2)``); ``DEFAULT_FOV_DEG`` when the scene names neither. ValueError
    for a lens of the other projection, or both lenses."""
    if fov_deg is not None and view_height is not None:
        raise ValueError("give fov_deg (perspective) or view_height (orthographic), not both")
    if projection == "orthographic" and fov_deg is not None:
        raise ValueError("an orthographic camera takes view_height, not fov_deg")
    if projection == "perspective" and view_height is not None:
        raise ValueError("a perspective camera takes fov_deg, not view_height")
    if projection is None:
        given = "orthographic" if view_height is not None else "perspective" if fov_deg is not None else None
        projection = given or ("orthographic" if "view_height" in camera else "perspective")
    distance = float(camera.get("distance", 2.0))
    if projection == "orthographic":
        if view_height is None:
            own = camera.get("view_height")
            fov = float(camera.get("fov_deg", DEFAULT_FOV_DEG))
            view_height = float(own) if own is not None else 2.0 * distance * math.tan(math.radians(0.5 * fov))
        return None, view_height
    if fov_deg is None:
        own = camera.get("view_height")
        fov_deg = (float(camera.get("fov_deg", DEFAULT_FOV_DEG)) if own is None
                   else math.degrees(2.0 * math.atan(0.5 * float(own) / distance)))
    return fov_deg, None

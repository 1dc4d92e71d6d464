"""The path document: what it reads, what it refuses (naming the field), and writing it back."""

import copy
import json
import math

import numpy as np
import pytest

from visnerf.animation.path import MAX_KEYFRAMES, AnimationPath, CameraKey, Keyframe, PathError, parse_path
from visnerf.checkpoint import ParamAxis
from visnerf.data.cameras import orbit_c2w

AXES = (ParamAxis("isovalue", 0.2, 0.8, (0.2, 0.5, 0.8), 0.5), ParamAxis("time", 0.0, 10.0, (0.0, 10.0), 5.0))
DEFAULTS = {"azimuth": 30.0, "elevation": 20.0, "distance": 2.5, "fov_deg": 30.0}


def good_doc() -> dict:
    return {
        "version": 1,
        "camera_interpolation": "smooth",
        "param_interpolation": "linear",
        "keyframes": [
            {"time": 0.0, "camera": {"azimuth": 30, "elevation": 15, "distance": 2.2, "fov": 30},
             "params": {"isovalue": 0.4}},
            {"time": 1.5, "camera": {"azimuth": -60, "elevation": -40, "distance": 3, "fov": 45},
             "params": {"isovalue": 0.8, "time": 2}},
            {"time": 2, "camera": {"azimuth": 10, "elevation": 90, "distance": 2.0, "fov": 20}},
        ],
    }


def test_a_good_document_reads_with_defaults_filled_in() -> None:
    path = parse_path(good_doc(), AXES, DEFAULTS)
    assert path.camera_interpolation == "smooth" and path.param_interpolation == "linear"
    assert path.duration == 2.0
    assert path.keyframes[1] == Keyframe(1.5, CameraKey(-60.0, -40.0, 3.0, 45.0), {"isovalue": 0.8, "time": 2.0})
    assert path.keyframes[0].params == {"isovalue": 0.4, "time": 5.0}  # time: the axis default
    assert path.keyframes[2].params == {"isovalue": 0.5, "time": 5.0}


def test_missing_camera_fields_take_the_scene_defaults() -> None:
    doc = {"version": 1, "keyframes": [{"time": 0, "camera": {"azimuth": 90}}, {"time": 1}]}
    path = parse_path(doc, AXES, DEFAULTS)
    assert path.keyframes[0].camera == CameraKey(90.0, 20.0, 2.5, 30.0)
    assert path.keyframes[1].camera == CameraKey(30.0, 20.0, 2.5, 30.0)
    assert (path.camera_interpolation, path.param_interpolation) == ("smooth", "linear")


def test_to_dict_reads_back_to_the_same_path_through_json() -> None:
    path = parse_path(good_doc(), AXES, DEFAULTS)
    again = parse_path(json.loads(json.dumps(path.to_dict())), AXES, DEFAULTS)
    assert again == path
    assert path.to_dict()["version"] == 1


def test_checkpoint_axes_work_as_well_as_inference_axes() -> None:
    axes = tuple(ParamAxis(a.name, a.min, a.max, a.values, a.default) for a in AXES)
    assert parse_path(good_doc(), axes, DEFAULTS) == parse_path(good_doc(), AXES, DEFAULTS)


def test_a_value_at_the_float32_end_of_a_range_is_clamped_not_refused() -> None:
    axes = (ParamAxis("omega", 0.12, float(np.float32(0.16)), (0.12, 0.16), 0.14),)  # 0.1599999964
    doc = {"version": 1, "keyframes": [{"time": 0, "params": {"omega": 0.16}}]}
    assert parse_path(doc, axes, DEFAULTS).keyframes[0].params["omega"] == float(np.float32(0.16))


@pytest.mark.parametrize(
    "az, el",
    [(30.0, 15.0), (-150.0, -60.0), (179.5, 0.0), (0.0, 90.0), (-120.0, 90.0), (45.0, -90.0)],
)
def test_c2w_keys_round_trip_to_the_same_camera(az: float, el: float) -> None:
    doc = {"version": 1, "keyframes": [{"time": 0, "camera": {"c2w": orbit_c2w(az, el, 2.7).tolist(), "fov": 40}}]}
    camera = parse_path(doc, AXES, DEFAULTS).keyframes[0].camera
    assert camera.elevation == pytest.approx(el, abs=1e-9) and camera.distance == pytest.approx(2.7)
    assert camera.fov == 40.0
    assert math.remainder(camera.azimuth - az, 360.0) == pytest.approx(0.0, abs=1e-9)  # at the poles too
    np.testing.assert_allclose(orbit_c2w(camera.azimuth, camera.elevation, camera.distance), orbit_c2w(az, el, 2.7),
                               atol=1e-12)


def test_a_c2w_camera_without_fov_takes_the_scene_fov() -> None:
    doc = {"version": 1, "keyframes": [{"time": 0, "camera": {"c2w": orbit_c2w(10.0, 10.0, 2.0).tolist()}}]}
    assert parse_path(doc, AXES, DEFAULTS).keyframes[0].camera.fov == 30.0


def turn_in_place(c2w: np.ndarray, degrees: float) -> np.ndarray:
    """The camera turned about its own y axis (its position kept): it looks ``degrees`` beside the origin."""
    a = math.radians(degrees)
    turn = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    out = c2w.copy()
    out[:3, :3] = c2w[:3, :3] @ turn
    return out


def malformed_cases() -> list[tuple[str, object, str]]:
    """(name, document, the start of the expected message)."""
    cases: list[tuple[str, object, str]] = []

    def case(name: str, edit, field: str) -> None:
        doc = good_doc()
        edited = edit(doc)
        cases.append((name, doc if edited is None else edited, field))

    case("not an object", lambda d: [d], "path: must be a JSON object")
    case("unknown top-level key", lambda d: d.update(speed=2), "speed: unknown key")
    case("no version", lambda d: d.pop("version") and None, "version: missing")
    case("version 2", lambda d: d.update(version=2), "version: must be 1")
    case("version true", lambda d: d.update(version=True), "version: must be 1")
    case("unknown camera interpolation", lambda d: d.update(camera_interpolation="bezier"), "camera_interpolation:")
    case("unknown param interpolation", lambda d: d.update(param_interpolation="cubic"), "param_interpolation:")
    case("keyframes not a list", lambda d: d.update(keyframes={"time": 0}), "keyframes: must be a list")
    case("empty keyframes", lambda d: d.update(keyframes=[]), "keyframes: must hold at least one")
    case("too many keyframes", lambda d: d.update(keyframes=[{"time": i} for i in range(MAX_KEYFRAMES + 1)]),
         f"keyframes: at most {MAX_KEYFRAMES}")
    case("keyframe not an object", lambda d: d["keyframes"].__setitem__(1, 3), "keyframes[1]: must be a JSON object")
    case("unknown keyframe key", lambda d: d["keyframes"][1].update(ease="in"), "keyframes[1].ease: unknown key")
    case("no time", lambda d: d["keyframes"][2].pop("time") and None, "keyframes[2].time: missing")
    case("string time", lambda d: d["keyframes"][1].update(time="1.5"), "keyframes[1].time: must be a number")
    case("boolean time", lambda d: d["keyframes"][1].update(time=True), "keyframes[1].time: must be a number")
    case("huge integer time", lambda d: d["keyframes"][2].update(time=10**400), "keyframes[2].time: must be a finite")
    case("negative time", lambda d: d["keyframes"][0].update(time=-1), "keyframes[0].time: must be >= 0")
    case("NaN time", lambda d: d["keyframes"][1].update(time=float("nan")), "keyframes[1].time: must be a finite")
    case("infinite time", lambda d: d["keyframes"][2].update(time=float("inf")), "keyframes[2].time: must be a finite")
    case("time going back", lambda d: d["keyframes"][2].update(time=1.0), "keyframes[2].time: must be after")
    case("time repeated", lambda d: d["keyframes"][1].update(time=0.0), "keyframes[1].time: must be after")
    case("camera not an object", lambda d: d["keyframes"][0].update(camera=[30, 15]), "keyframes[0].camera: must be")
    case("unknown camera key", lambda d: d["keyframes"][0]["camera"].update(roll=3), "keyframes[0].camera.roll:")
    case("elevation 120", lambda d: d["keyframes"][2]["camera"].update(elevation=120),
         "keyframes[2].camera.elevation: must be in [-90, 90], got 120")
    case("distance 0", lambda d: d["keyframes"][1]["camera"].update(distance=0), "keyframes[1].camera.distance:")
    case("fov 180", lambda d: d["keyframes"][1]["camera"].update(fov=180), "keyframes[1].camera.fov: must be in")
    case("boolean azimuth", lambda d: d["keyframes"][0]["camera"].update(azimuth=False),
         "keyframes[0].camera.azimuth: must be a number")
    case("null fov", lambda d: d["keyframes"][0]["camera"].update(fov=None), "keyframes[0].camera.fov: must be a num")
    case("infinite azimuth", lambda d: d["keyframes"][0]["camera"].update(azimuth=float("-inf")),
         "keyframes[0].camera.azimuth: must be a finite")
    case("c2w and azimuth", lambda d: d["keyframes"][0].update(
        camera={"c2w": orbit_c2w(0.0, 0.0, 2.0).tolist(), "azimuth": 3}), "keyframes[0].camera.azimuth: unknown key")
    case("c2w 3x4", lambda d: d["keyframes"][0].update(camera={"c2w": orbit_c2w(0.0, 0.0, 2.0).tolist()[:3]}),
         "keyframes[0].camera.c2w: must be 4 rows of 4 numbers")
    case("c2w with a string", lambda d: d["keyframes"][0].update(
        camera={"c2w": [["1", 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2], [0, 0, 0, 1]]}),
        "keyframes[0].camera.c2w[0][0]: must be a number")
    case("c2w not rigid", lambda d: d["keyframes"][1].update(camera={"c2w": (orbit_c2w(0.0, 0.0, 2.0) * 1.5).tolist()}),
         "keyframes[1].camera.c2w: not a rigid")
    case("c2w looking away", lambda d: d["keyframes"][1].update(
        camera={"c2w": turn_in_place(orbit_c2w(30.0, 10.0, 2.0), 2.0).tolist()}),
        "keyframes[1].camera.c2w: the camera looks 2.00 degrees away")
    case("c2w at the origin", lambda d: d["keyframes"][1].update(camera={"c2w": np.eye(4).tolist()}),
         "keyframes[1].camera.c2w: the camera sits on the origin")
    case("params not an object", lambda d: d["keyframes"][0].update(params=[0.4]), "keyframes[0].params: must be")
    case("unknown parameter", lambda d: d["keyframes"][1]["params"].update(density=1),
         "keyframes[1].params.density: unknown parameter")
    case("parameter above max", lambda d: d["keyframes"][1]["params"].update(isovalue=0.9),
         "keyframes[1].params.isovalue: must be in [0.2, 0.8], got 0.9")
    case("parameter below min", lambda d: d["keyframes"][0]["params"].update(time=-0.5),
         "keyframes[0].params.time: must be in [0, 10], got -0.5")
    case("boolean parameter", lambda d: d["keyframes"][0]["params"].update(isovalue=True),
         "keyframes[0].params.isovalue: must be a number")
    return cases


@pytest.mark.parametrize("name, doc, message", malformed_cases(), ids=[c[0] for c in malformed_cases()])
def test_a_malformed_path_is_refused_naming_the_field(name: str, doc: object, message: str) -> None:
    with pytest.raises(PathError) as caught:
        parse_path(copy.deepcopy(doc), AXES, DEFAULTS)
    assert str(caught.value).startswith(message), str(caught.value)


def test_a_c2w_looking_within_a_degree_of_the_origin_is_taken() -> None:
    c2w = turn_in_place(orbit_c2w(30.0, 10.0, 2.0), 0.5)
    doc = {"version": 1, "keyframes": [{"time": 0, "camera": {"c2w": c2w.tolist()}}]}
    assert parse_path(doc, AXES, DEFAULTS).keyframes[0].camera.distance == pytest.approx(2.0)


def test_a_missing_camera_field_without_a_scene_default_is_named() -> None:
    with pytest.raises(PathError, match=r"^keyframes\[0\]\.camera\.fov: missing"):
        parse_path({"version": 1, "keyframes": [{"time": 0}]}, AXES, {"azimuth": 0.0, "elevation": 0.0,
                                                                       "distance": 2.0})


def test_built_paths_are_checked_as_well() -> None:
    cam = CameraKey(0.0, 0.0, 2.0, 30.0)
    with pytest.raises(PathError, match=r"^keyframes: must hold at least one"):
        AnimationPath(())
    with pytest.raises(PathError, match=r"^keyframes\[1\]\.time: must be after"):
        AnimationPath((Keyframe(1.0, cam, {}), Keyframe(1.0, cam, {})))
    with pytest.raises(PathError, match=r"^camera_interpolation"):
        AnimationPath((Keyframe(0.0, cam, {}),), camera_interpolation="cubic")
    with pytest.raises(PathError, match=r"^camera\.elevation: must be in \[-90, 90\], got 91"):
        CameraKey(0.0, 91.0, 2.0, 30.0)

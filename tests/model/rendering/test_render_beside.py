"""A scene's frames run beside each other (``inference.SceneRenderer``): neither a preview nor a
second full frame waits for a full frame in progress, and frames rendered at once equal frames
rendered alone."""

import threading

import numpy as np

from visnerf.data.cameras import orbit_c2w
from visnerf.inference import load_scene
from visnerf.testing import make_tiny_checkpoint


def test_a_preview_and_a_full_frame_finish_while_a_full_frame_of_their_scene_is_held(tmp_path) -> None:
    scene = load_scene(make_tiny_checkpoint(tmp_path / "s.safetensors"))
    c2w = orbit_c2w(20.0, 30.0, 2.2)
    inside, release = threading.Event(), threading.Event()

    def hold() -> bool:  # the full frame's cancel check: it stops there until released
        inside.set()
        release.wait(30.0)
        return False

    full: dict[str, object] = {}

    def render_full() -> None:
        full["rgb"] = scene.render(c2w, 40.0, 32, 32, {"a": 0.5}, "full", cancel=hold)

    worker = threading.Thread(target=render_full)
    worker.start()
    try:
        assert inside.wait(30.0), "the full frame never started"
        preview: dict[str, np.ndarray] = {}
        side = threading.Thread(target=lambda: preview.update(rgb=scene.render(c2w, 40.0, 32, 32, {"a": 0.5}, "preview")))
        side.start()
        side.join(30.0)
        assert not side.is_alive(), "the preview waited for the full frame"
        assert preview["rgb"].shape == (32, 32, 3)
        assert worker.is_alive(), "the full frame was not held while the preview ran"
        # a second full frame of the same scene does not wait for the first either
        second: dict[str, np.ndarray] = {}
        other = threading.Thread(target=lambda: second.update(rgb=scene.render(c2w, 40.0, 32, 32, {"a": 0.5}, "full")))
        other.start()
        other.join(30.0)
        assert not other.is_alive(), "the second full frame waited for the first"
        assert worker.is_alive(), "the first full frame was not held while the second ran"
    finally:
        release.set()
        worker.join(30.0)
    assert not worker.is_alive()
    np.testing.assert_array_equal(full["rgb"], second["rgb"])
    np.testing.assert_array_equal(full["rgb"], scene.render(c2w, 40.0, 32, 32, {"a": 0.5}, "full"))

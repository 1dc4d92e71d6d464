"""The scene registry: the checkpoints folder, loaded and validated, keyed by scene id.

A scene id is the file stem of ``<id>.safetensors`` and must match ``SCENE_ID_PATTERN``; anything
else in the folder (hidden upload temporaries, other files) is ignored. Mutations (upload commit,
delete) hold ``mutation_lock`` so the folder and the registry change together.
"""

import hashlib
import logging
import re
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from visnerf.config import FramesConfig
from visnerf.data.cameras import orbit_c2w
from visnerf.inference import SceneRenderer, choose_lens, load_scene

logger = logging.getLogger(__name__)

SCENE_ID_PATTERN = r"^[a-z0-9][a-z0-9_-]{0,63}$"
CHECKPOINT_SUFFIX = ".safetensors"
_SCENE_ID_RE = re.compile(SCENE_ID_PATTERN)

PROBE_SIZE = 8
"""Width and height of the test render every scene passes before it is served."""


def is_valid_scene_id(scene_id: str) -> bool:
    return _SCENE_ID_RE.fullmatch(scene_id) is not None


_ABSOLUTE_PATH_RE = re.compile(r"(?<![\w.~:/])/(?:[^\s'\"/:,;()\[\]]+/)*([^\s'\"/:,;()\[\]]*)")
"""A POSIX absolute path in a message; group 1 is its last part (the file name)."""


def public_error(exc: BaseException, folder: Path | None = None) -> str:
    """``Type: message`` with ``folder`` and every other absolute path cut to the file name:
    ``/api/ready`` shows which file failed and why, not where the server keeps its files."""
    message = str(exc)
    if folder is not None:
        for prefix in {str(folder), str(folder.resolve())}:
            message = message.replace(prefix.rstrip("/") + "/", "")
    return f"{type(exc).__name__}: {_ABSOLUTE_PATH_RE.sub(lambda m: m.group(1), message)}"


@dataclass(frozen=True)
class Scene:
    """One servable scene."""

    id: str
    renderer: SceneRenderer
    path: Path
    version: str
    """Content hash of the checkpoint file; changes when the scene is replaced."""


def file_digest(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def default_view(renderer: SceneRenderer) -> np.ndarray:
    """The scene's default camera pose (c2w); its lens is ``inference.choose_lens`` of its camera."""
    camera = renderer.info.camera
    return orbit_c2w(
        float(camera.get("azimuth", 0.0)),
        float(camera.get("elevation", 0.0)),
        float(camera.get("distance", 4.0)),
    )


def probe_render(renderer: SceneRenderer) -> None:
    """Render one tiny frame from the default view; raises ValueError if the result is malformed."""
    fov_deg, view_height = choose_lens(renderer.info.camera)
    image = renderer.render(default_view(renderer), fov_deg, PROBE_SIZE, PROBE_SIZE, {}, "preview",
                            view_height=view_height)
    if image.shape != (PROBE_SIZE, PROBE_SIZE, 3) or image.dtype != np.uint8:
        raise ValueError(f"test render returned {image.dtype} {list(image.shape)}, expected uint8 [8, 8, 3]")


def load_and_check(path: Path, device: torch.device, frames: FramesConfig | None = None) -> SceneRenderer:
    """Load a checkpoint with every check ``load_scene`` runs, then a test render."""
    renderer = load_scene(path, device, frames)
    probe_render(renderer)
    return renderer


class SceneRegistry:
    """Scenes by id. Reads are lock-free snapshots; writes hold ``mutation_lock``."""

    def __init__(self, checkpoints_dir: Path, device: torch.device, frames: FramesConfig | None = None) -> None:
        self.checkpoints_dir = checkpoints_dir
        self.device = device
        self.frames = frames or FramesConfig()
        """How this server renders frames: chunks of rays, per-setting grids (``Settings.frames``)."""
        self.mutation_lock = threading.Lock()
        self._scenes: dict[str, Scene] = {}
        self._lock = threading.Lock()
        self.loading = True
        """True until the first ``load_all`` has finished: an unknown id may still be on its way."""
        self.watched = False
        """True once a store watcher (``store_watch``) follows the folder: a file there that is not
        served yet is on its way too."""
        self.unservable: frozenset[str] = frozenset()
        """Ids whose file failed its checks (the watcher keeps this): not on their way."""

    def load(self, path: Path, check: bool = True) -> SceneRenderer:
        """The scene in ``path`` as this server renders it; ``check``: and a test render
        (``load_and_check``)."""
        return load_and_check(path, self.device, self.frames) if check else load_scene(path, self.device, self.frames)

    def path_for(self, scene_id: str) -> Path:
        if not is_valid_scene_id(scene_id):
            raise ValueError(f"invalid scene id {scene_id!r}: must match {SCENE_ID_PATTERN}")
        return self.checkpoints_dir / f"{scene_id}{CHECKPOINT_SUFFIX}"

    def scan(self) -> list[tuple[str, Path]]:
        """Checkpoint files with valid ids, sorted by id."""
        if not self.checkpoints_dir.is_dir():
            return []
        found = []
        for path in sorted(self.checkpoints_dir.glob(f"*{CHECKPOINT_SUFFIX}")):
            scene_id = path.name[: -len(CHECKPOINT_SUFFIX)]
            if is_valid_scene_id(scene_id) and path.is_file():
                found.append((scene_id, path))
            elif not scene_id.startswith("."):
                logger.warning("ignoring %s: scene ids must match %s", path.name, SCENE_ID_PATTERN)
        return found

    def load_all(self, warmup: bool = True, stop: threading.Event | None = None) -> dict[str, str]:
        """Load every checkpoint in the folder; returns {id: error} for those that failed (skipped).

        ``stop`` (set at shutdown) ends the loop between scenes."""
        errors: dict[str, str] = {}
        for scene_id, path in self.scan():
            if stop is not None and stop.is_set():
                break
            try:
                version = file_digest(path)
                renderer = self.load(path, warmup)
            except Exception as exc:  # a bad file on disk must not stop the others from loading
                errors[scene_id] = public_error(exc, self.checkpoints_dir)
                logger.error("scene %r not loaded from %s: %s", scene_id, path, exc)
                continue
            with self.mutation_lock:
                if path.exists() and scene_id not in self._scenes:  # not deleted/replaced meanwhile
                    self.install(Scene(scene_id, renderer, path, version))
            logger.info("scene %r loaded from %s", scene_id, path)
        self.unservable = frozenset(errors)
        self.loading = False
        return errors

    def pending(self, scene_id: str) -> bool:
        """Whether ``scene_id`` is unknown only because its file has not been loaded yet: the
        folder's first load is running, or the store watcher has yet to check a new file."""
        if scene_id in self._scenes or not is_valid_scene_id(scene_id):
            return False
        if not (self.loading or self.watched) or scene_id in self.unservable:
            return False
        return self.path_for(scene_id).is_file()

    def get(self, scene_id: str) -> Scene | None:
        return self._scenes.get(scene_id)

    def list(self) -> list[Scene]:
        with self._lock:
            return sorted(self._scenes.values(), key=lambda s: s.id)

    def __len__(self) -> int:
        return len(self._scenes)

    def install(self, scene: Scene) -> bool:
        """Add or replace a scene (caller holds ``mutation_lock``); True when it replaced one."""
        with self._lock:
            replaced = scene.id in self._scenes
            self._scenes[scene.id] = scene
        return replaced

    def remove(self, scene_id: str) -> Scene | None:
        """Forget a scene (caller holds ``mutation_lock``)."""
        with self._lock:
            return self._scenes.pop(scene_id, None)

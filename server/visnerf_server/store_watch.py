"""The store watcher: keeps this server's scenes equal to the checkpoints folder when other
``visnerf serve`` processes (replicas behind a load balancer) upload and delete in the same folder.

Every ``Settings.store_poll_s`` seconds a thread lists ``<id>.safetensors`` (``SceneRegistry.scan``:
hidden upload temporaries and other names are never looked at) and compares each file's signature
(size, mtime, inode) with the one it last handled:

- a file gone: its scene is dropped (and its readiness error forgotten);
- a new or changed file whose SHA-256 is the served scene's version (an upload through this server,
  a ``touch``): nothing to load;
- any other new or changed file is loaded only once its signature has stayed the same for one whole
  poll (a file copied in place is not read while it grows), through the checks every upload passes
  (``registry.load_and_check``), then installed if the file still has the signature it had before
  the load. Uploads write a temporary file and rename it into place, so a reader sees the old file
  or the new one, never half of one; of two uploads of one id the last rename wins everywhere.
- a file that fails its checks is named in ``/api/ready``'s ``failed`` (and its old scene dropped,
  as a server started now would not serve it); it is tried again when it changes.
- a folder that cannot be read (a share gone away) changes nothing: it is not an empty store.

A new or changed file is served within two polls and its load. Until then a request for a new id
answers 503 with Retry-After (``SceneRegistry.pending``), which a proxy retries on another replica.
"""

import logging
import os
import threading
from dataclasses import dataclass, field
from pathlib import Path

from visnerf_server.dependencies import ServerState
from visnerf_server.registry import Scene, file_digest, public_error

logger = logging.getLogger(__name__)

Signature = tuple[int, int, int]
"""(size, mtime in ns, inode) of a checkpoint file: a rename into place or a write changes it."""
JOIN_TIMEOUT_S = 5.0


def signature(path: Path) -> Signature | None:
    """The file's signature, or None when it is gone."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_size, st.st_mtime_ns, st.st_ino)


@dataclass
class StoreWatcher:
    """Compares the folder with the registry, one ``poll`` at a time (``run`` loops until ``stop``)."""

    server: ServerState
    stop: threading.Event
    handled: dict[str, Signature] = field(default_factory=dict)
    """Per id, the signature of the file last installed, found equal to the served scene, or
    found bad: nothing to do until it changes."""
    settling: dict[str, Signature] = field(default_factory=dict)
    """Per id, the signature of a new or changed file seen at the last poll."""
    unreadable: bool = False
    """The folder could not be listed at the last poll (said once in the log)."""

    def __post_init__(self) -> None:
        self.server.registry.watched = True

    def run(self) -> None:
        while not self.stop.wait(self.server.settings.store_poll_s):
            if not self.server.ready:  # the start-up load is still running
                continue
            try:
                self.poll()
            except Exception:  # a surprise must not end the watching
                logger.exception("checkpoints folder poll failed")

    def poll(self) -> None:
        """Compare the folder with the registry once; drop, load and install what differs."""
        registry = self.server.registry
        try:
            os.listdir(registry.checkpoints_dir)
        except OSError as exc:  # an unmounted share is not an empty store: keep serving
            if not self.unreadable:
                logger.warning("checkpoints folder unreadable, scenes kept as they are: %s", exc)
            self.unreadable = True
            return
        self.unreadable = False
        registry.unservable = frozenset(self.server.load_errors)  # the start-up load's too
        files = {scene_id: (path, sig) for scene_id, path in registry.scan() if (sig := signature(path)) is not None}
        for scene in registry.list():
            if scene.id not in files:
                self._drop(scene.id)
        for scene_id in set(self.handled) | set(self.settling) | set(self.server.load_errors):
            if scene_id not in files:
                self.handled.pop(scene_id, None)
                self.settling.pop(scene_id, None)
                self._set_error(scene_id, None)
        for scene_id, (path, sig) in files.items():
            if self.stop.is_set():
                return
            if self.handled.get(scene_id) == sig or self._already_served(scene_id, path, sig):
                continue
            if self.settling.get(scene_id) == sig:  # unchanged for a whole poll: read it
                self._load(scene_id, path, sig)
            else:
                self.settling[scene_id] = sig

    def _already_served(self, scene_id: str, path: Path, sig: Signature) -> bool:
        """Whether the file is the scene this server serves already (its own upload, a touch)."""
        scene = self.server.registry.get(scene_id)
        if scene is None:
            return False
        try:
            same = file_digest(path) == scene.version
        except OSError:
            return False
        if same:
            self.handled[scene_id] = sig
            self.settling.pop(scene_id, None)
            self._set_error(scene_id, None)
        return same

    def _load(self, scene_id: str, path: Path, sig: Signature) -> None:
        registry = self.server.registry
        try:
            version = file_digest(path)
            renderer = registry.load(path, self.server.settings.warmup)
        except Exception as exc:  # the file's fault: report it, serve nothing of it
            if signature(path) != sig:  # changed while being read: settle again
                self.settling.pop(scene_id, None)
                return
            logger.error("scene %r not loaded from %s: %s", scene_id, path, exc)
            with registry.mutation_lock:
                if signature(path) == sig:
                    registry.remove(scene_id)
                    self.handled[scene_id] = sig
            self.settling.pop(scene_id, None)
            self._set_error(scene_id, public_error(exc, registry.checkpoints_dir))
            self._changed(scene_id)
            return
        with registry.mutation_lock:  # uploads rename and install under it: the file is the one read
            installed = signature(path) == sig
            if installed:
                replaced = registry.install(Scene(scene_id, renderer, path, version))
                self.handled[scene_id] = sig
        self.settling.pop(scene_id, None)
        if installed:
            self._set_error(scene_id, None)
            self._changed(scene_id)
            logger.info("scene %r %s from the checkpoints folder", scene_id, "reloaded" if replaced else "loaded")

    def _drop(self, scene_id: str) -> None:
        registry = self.server.registry
        with registry.mutation_lock:
            if registry.path_for(scene_id).exists():  # put back meanwhile (an upload here)
                return
            registry.remove(scene_id)
        self._changed(scene_id)
        logger.info("scene %r dropped: its file left the checkpoints folder", scene_id)

    def _changed(self, scene_id: str) -> None:
        self.server.cache.drop_scene(scene_id)
        if self.server.bakes is not None:
            self.server.bakes.drop_scene(scene_id)
        self.server.metrics.scenes.set(len(self.server.registry))

    def _set_error(self, scene_id: str, error: str | None) -> None:
        """Name (or stop naming) a bad file in readiness; the dict is swapped, never mutated."""
        errors = self.server.load_errors
        if errors.get(scene_id) == error:
            return
        updated = {k: v for k, v in errors.items() if k != scene_id}
        if error is not None:
            updated[scene_id] = error
        self.server.load_errors = dict(sorted(updated.items()))
        self.server.registry.unservable = frozenset(updated)


def start_store_watcher(server: ServerState, stop: threading.Event) -> threading.Thread | None:
    """The watcher's thread, started (it polls once the start-up load is done); None when
    ``store_poll_s`` is 0."""
    if server.settings.store_poll_s <= 0:
        return None
    watcher = StoreWatcher(server, stop)
    thread = threading.Thread(target=watcher.run, name="visnerf-store-watcher", daemon=True)
    thread.start()
    return thread

"""Parallel renders while one checkpoint is uploaded and another deleted: no errors, no partial
files, every response well formed."""

import json
import shutil
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from fastapi.testclient import TestClient
from server_helpers import AUTH, ORBIT, image_size, listing, scene_ids


def test_renders_during_upload_and_delete(client: TestClient, ckpt_dir: Path, templates) -> None:
    shutil.copy(templates["tiny"], ckpt_dir / "victim.safetensors")
    registry = client.app.state.server.registry
    registry.load_all(warmup=False)  # pick up the extra file
    assert scene_ids(client) == ["tiny", "two", "victim"]
    upload_bytes = templates["other"].read_bytes()
    stop = threading.Event()
    problems: list[str] = []
    counts = {"ok": 0, "gone": 0, "stable_asked": 0, "stable_ok": 0}
    lock = threading.Lock()
    started = threading.Event()

    def check(response, scene: str, fmt: str, width: int) -> None:
        stable = scene in ("tiny", "two")  # neither uploaded nor deleted: every render must succeed
        with lock:
            counts["stable_asked"] += stable
            counts["stable_ok"] += stable and response.status_code == 200
        if response.status_code == 200:
            kind, w, h = image_size(response.content)
            if (kind.lower(), w, h) != (fmt, width, 16):
                problems.append(f"{scene}: got {kind} {w}x{h}")
            with lock:
                counts["ok"] += 1
                if counts["ok"] >= 4:
                    started.set()
        elif response.status_code == 404 and scene in ("victim", "newbie"):
            assert json.loads(response.content)["detail"] == f"unknown scene {scene!r}"
            with lock:
                counts["gone"] += 1
        elif response.status_code == 503 and scene == "newbie":
            # The upload's file is in the folder, its scene not yet installed: a retry is asked for.
            assert json.loads(response.content)["detail"] == f"scene {scene!r} is still loading"
            assert response.headers.get("retry-after") is not None
            with lock:
                counts["gone"] += 1
        else:
            problems.append(f"{scene}: {response.status_code} {response.text[:200]}")

    def renderer(worker: int) -> None:
        i = 0
        while not stop.is_set() or i < 10:
            scene = ("tiny", "victim", "newbie", "two")[(worker + i) % 4]
            fmt = ("png", "jpeg")[i % 2]
            width = 8 + (i % 5)  # vary the size so the cache does not answer everything
            try:
                if i % 3 == 0:
                    response = client.get(
                        f"/api/scenes/{scene}/render",
                        params={**ORBIT, "width": width, "height": 16, "format": fmt},
                    )
                else:
                    response = client.post(
                        f"/api/scenes/{scene}/render",
                        json={
                            "camera": {**ORBIT, "azimuth": float(i)},
                            "width": width,
                            "height": 16,
                            "format": fmt,
                        },
                    )
                check(response, scene, fmt, width)
            except Exception as exc:  # any exception is a failure to report
                problems.append(f"{scene}: {type(exc).__name__}: {exc}")
            i += 1

    def upload() -> int:
        return client.put("/api/scenes/newbie", content=upload_bytes, headers=AUTH).status_code

    def delete() -> int:
        return client.delete("/api/scenes/victim", headers=AUTH).status_code

    with ThreadPoolExecutor(max_workers=6) as pool:
        workers = [pool.submit(renderer, w) for w in range(4)]
        try:
            assert started.wait(30), problems[:3]  # renders are under way before the folder changes
            uploaded = pool.submit(upload)
            deleted = pool.submit(delete)
            assert uploaded.result(60) == 201
            assert deleted.result(60) == 204
        finally:
            stop.set()  # a failure above must not leave the renderers looping (the pool waits for them)
        for w in workers:
            w.result(60)

    assert problems == []
    # What happened, not how fast: each of the 4 workers sent at least 10 requests, half of them to
    # the two scenes that stayed, and every one of those was rendered.
    assert counts["stable_ok"] == counts["stable_asked"] >= 20
    assert counts["ok"] + counts["gone"] >= 40
    assert scene_ids(client) == ["newbie", "tiny", "two"]
    assert listing(ckpt_dir) == ["newbie.safetensors", "tiny.safetensors", "two.safetensors"]
    assert (ckpt_dir / "newbie.safetensors").read_bytes() == upload_bytes
    response = client.post("/api/scenes/newbie/render", json={"camera": ORBIT, "width": 8, "height": 16})
    assert response.status_code == 200
    server = client.app.state.server
    assert server.queue.waiting == 0 and server.queue.running == 0

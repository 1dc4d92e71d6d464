"""GET /api/limits names the largest frames the server renders, so that a client sizes frames to
its screen within them; a frame just over them is refused."""

from fastapi.testclient import TestClient
from server_helpers import make_settings

from visnerf_server.app import create_app


def test_limits_are_the_settings_and_hold(ckpt_dir, tmp_path) -> None:
    settings = make_settings(ckpt_dir, tmp_path / "state", max_image_size=300, max_full_pixels=250 * 250)
    with TestClient(create_app(settings)) as client:
        limits = client.get("/api/limits").json()
        assert limits == {"max_side": 300, "max_full_pixels": 62500,
                          "max_preview_pixels": settings.max_preview_pixels}
        fits = client.get("/api/scenes/tiny/render", params={"width": 250, "height": 250})
        assert fits.status_code == 200, fits.text
        wide = client.get("/api/scenes/tiny/render", params={"width": 301, "height": 16})
        big = client.get("/api/scenes/tiny/render", params={"width": 251, "height": 250})
        assert wide.status_code == big.status_code == 422
        assert "300" in wide.text and "max_full_pixels" in big.text
        assert "/api/limits" in client.get("/openapi.json").json()["paths"]

"""Take the README's screenshot of the web client (docs/images/client.png, 1280x800).

    python tests/client/readme_screenshot.py [--checkpoints DIR --scene ID --param NAME]

It serves the bundled checkpoints (``checkpoints/``) unless ``--checkpoints`` names another folder. The page is put in comparison mode (B pinned at the current
parameters, then A's first parameter moved to its maximum) so the shot shows the sliders, the
training-value ticks, the A/B views and the CIELUV difference with its legend.
"""

import argparse
import sys
from pathlib import Path

from conftest import CHROMIUM, CHROMIUM_ARGS, REPO, start_server

OUT = REPO / "docs" / "images" / "client.png"
SETTLED = "window.__visnerfSettled && window.__visnerfSettled()"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--checkpoints", type=Path, default=REPO / "checkpoints")
    parser.add_argument("--scene")
    parser.add_argument("--param", help="parameter to move for the comparison (default: the first)")
    parser.add_argument("--scale", default="5", help="legend scale (dE*uv at the top)")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)

    from playwright.sync_api import sync_playwright

    server = start_server(args.checkpoints, "screenshot")
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            query = f"?scene={args.scene}" if args.scene else ""
            page.goto(f"{server.base_url}/{query}")
            page.wait_for_function(SETTLED, timeout=60_000)
            page.click("#pin-b")
            param = args.param or page.locator('.param[data-set="A"]').first.get_attribute("data-param")
            page.locator(f'.param[data-set="A"][data-param="{param}"] input[type=range]').focus()
            page.keyboard.press("End")
            page.select_option("#diff-scale", args.scale)
            page.wait_for_timeout(300)
            page.wait_for_function(SETTLED, timeout=60_000)
            page.evaluate("document.activeElement && document.activeElement.blur()")
            page.mouse.move(0, 0)
            args.out.parent.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(args.out))
            browser.close()
    finally:
        server.stop()
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

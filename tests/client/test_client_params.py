"""Parameter sliders built from the server's axes, and the A/B comparison with its difference image."""

import pytest
from client_helpers import assert_changed, canvas_pixels, get_json, wait_for_full_frame

pytestmark = [pytest.mark.browser, pytest.mark.slow]

ROW = '.param[data-set="A"][data-param="{}"]'


def test_sliders_match_the_scene_axes(page, base_url):
    scene = get_json(base_url + "/api/scenes/vortex_tf1")
    page.goto(base_url + "/?scene=vortex_tf1&res=128")
    wait_for_full_frame(page)
    rows = page.locator('.param[data-set="A"]')
    assert rows.count() == len(scene["params"])
    for i, axis in enumerate(scene["params"]):
        row = rows.nth(i)
        assert row.get_attribute("data-param") == axis["name"]
        assert row.locator("label").inner_text() == axis["name"]
        slider = row.locator("input[type=range]")
        assert float(slider.get_attribute("min")) == pytest.approx(axis["min"])
        assert float(slider.get_attribute("max")) == pytest.approx(axis["max"])
        list_id = slider.get_attribute("list")
        options = page.locator(f"datalist#{list_id} option").evaluate_all(
            "os => os.map(o => Number(o.value))"
        )
        assert options == pytest.approx(axis["values"])
        ticks = row.locator(".tick").evaluate_all("ts => ts.map(t => Number(t.dataset.value))")
        assert ticks == pytest.approx(axis["values"])
        # Drawn ticks sit at the training values' positions along the track.
        positions = row.locator(".tick").evaluate_all("ts => ts.map(t => t.getBoundingClientRect().x)")
        assert positions == sorted(positions)
        number = row.locator("input[type=number]")
        assert float(number.input_value()) == pytest.approx(axis["default"])
        assert slider.get_attribute("aria-valuetext").startswith(axis["name"])


def test_moving_a_slider_changes_the_picture(page, base_url):
    page.goto(base_url + "/?scene=vortex_tf1&res=128")
    seq = wait_for_full_frame(page)
    before = canvas_pixels(page)
    slider = page.locator(ROW.format("opacity_high") + " input[type=range]")
    slider.focus()
    for _ in range(6):
        page.keyboard.press("PageUp")  # a tenth of the range each
        page.wait_for_timeout(30)
    seq = wait_for_full_frame(page, seq)
    page.wait_for_function("new URL(location.href).searchParams.get('opacity_high') !== null")
    value = float(page.input_value(ROW.format("opacity_high") + " input[type=number]"))
    assert value > 0.5
    after = canvas_pixels(page)
    assert_changed(before, after)
    # Dragging the slider thumb with the mouse streams previews, then one full frame.
    box = slider.bounding_box()
    y = box["y"] + box["height"] / 2
    page.mouse.move(box["x"] + box["width"] - 7, y)
    page.mouse.down()
    for i in range(1, 16):
        page.mouse.move(box["x"] + box["width"] * (1 - i / 16), y)
        page.wait_for_timeout(25)
    page.mouse.up()
    wait_for_full_frame(page, seq)
    assert float(page.input_value(ROW.format("opacity_high") + " input[type=number]")) < 0.2
    qualities = page.evaluate("window.__visnerfStats.frames.map(f => f.quality)")
    assert "preview" in qualities and qualities[-1] == "full"


def test_typed_value_is_exact_and_kept_in_range(page, base_url):
    page.goto(base_url + "/?scene=vortex_tf1&res=128")
    seq = wait_for_full_frame(page)
    number = page.locator(ROW.format("opacity_low") + " input[type=number]")
    number.fill("0.1137")
    number.press("Enter")
    seq = wait_for_full_frame(page, seq)
    page.wait_for_function("new URL(location.href).searchParams.get('opacity_low') === '0.1137'")
    number.fill("5")
    number.press("Enter")
    assert number.input_value() == "0.2"  # clamped to the axis maximum
    wait_for_full_frame(page, seq)
    page.wait_for_function("new URL(location.href).searchParams.get('opacity_low') === '0.2'")
    assert page.locator(ROW.format("opacity_low")).evaluate("r => r.classList.contains('at-training-value')")


def test_compare_shows_the_cieluv_difference(page, base_url):
    page.goto(base_url + "/?scene=vortex_tf1&res=128")
    wait_for_full_frame(page)
    page.click("#pin-b")  # B = current parameters; comparison switches on
    assert page.locator("#pane-b").is_visible() and page.locator("#pane-diff").is_visible()
    wait_for_full_frame(page, selector="#canvas-b")
    page.wait_for_function("document.querySelector('#canvas-diff').dataset.max !== undefined")
    assert float(page.get_attribute("#canvas-diff", "data-max")) == 0.0, "A and B are equal: no difference"
    # Move A's opacity_high to its maximum: the difference image lights up.
    slider = page.locator(ROW.format("opacity_high") + " input[type=range]")
    slider.focus()
    page.keyboard.press("End")
    page.wait_for_function(
        """() => {
            const c = document.querySelector('#canvas-diff');
            const a = document.querySelector('#canvas-a');
            return Number(c.dataset.mean) > 0 && a.dataset.quality === 'full';
        }"""
    )
    page.wait_for_function("document.querySelector('#badge-diff').textContent === 'full'")
    assert "ΔE*uv mean" in page.inner_text("#diff-summary")
    diff = canvas_pixels(page, "#canvas-diff")
    assert diff.std() > 0.5
    # The legend is drawn and labelled with its scale, and the scale can change.
    ticks = page.locator("#legend-ticks span").all_inner_texts()
    assert ticks[0] == "0" and ticks[-1] == "≥20"
    page.select_option("#diff-scale", "80")
    assert page.locator("#legend-ticks span").all_inner_texts()[-1] == "≥80"
    legend = canvas_pixels(page, "#legend-bar")
    assert legend[:, 0].mean() < legend[:, -1].mean()
    # B keeps its own sliders; the URL carries the comparison.
    assert page.locator('.param[data-set="B"]').count() == 2
    page.wait_for_function("new URL(location.href).searchParams.get('cmp') === '1'")
    assert "b.opacity_high=" in page.url

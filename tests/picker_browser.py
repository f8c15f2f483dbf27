"""Drive the picker page in a headless Chromium as a person would (Playwright), for tests/test_picker.py.

Standalone (standard library + ``playwright`` only), so it runs under any Python that has Playwright::

    python tests/picker_browser.py URL PLAN.json SCREENSHOT.png [--chromium /usr/bin/chromium]

PLAN.json: ``{"car": "6223", "point": "front_door_top_front_left", "face": "left", "view": "pano_01.jpg",
"first_uv": [u, v], "uv": [u, v]}``. The run: choose the photo and the carriage, click the point on the
model's face, click ``first_uv`` in the photo (a rough pick), zoom in with the wheel at ``uv`` and click it
(the careful pick), undo it (Ctrl+Z: back to the rough pick), pick ``uv`` again, optionally reject the
automatic point of ``reject_point`` (R), save (Ctrl+S), take a screenshot. Prints a JSON summary (status line after each step) on stdout.

``--look``: PLAN.json ``{"view", "car"[, "point", "zoom": [u, v, scale], "edges": [[[u, v], [u, v]], [[u, v],
[u, v]]]]}``: choose the photo and the carriage, wait for the solve's overlay and the live pose, optionally pick
``point`` from two edges dragged in the photo (E), zoom in at ``(u, v)``, take a screenshot; prints what the page
shows (the overlay's and the live pose's figures, the checks panel's text).
"""

from __future__ import annotations

import argparse
import json
import sys


def _screen(page, uv):
    """Page coordinates of image pixel ``uv`` on the photo canvas (inverse of picker.js toImage)."""
    return page.evaluate(
        """([u, v]) => { const S = window.pickerState, r = document.getElementById('photo-canvas').getBoundingClientRect();
             return [r.left + (u + 0.5) * S.scale + S.ox, r.top + (v + 0.5) * S.scale + S.oy]; }""", list(uv))


def open_page(p, url: str, chromium: str | None, width: int, height: int):
    """(browser, page, errors): Chromium (``chromium``, else Playwright's own) with a page of that size at ``url``;
    ``errors`` collects the page's console errors and uncaught exceptions (a script error or a resource the page's
    CSP refused shows there)."""
    browser = p.chromium.launch(executable_path=chromium, args=["--no-sandbox"]) if chromium \
        else p.chromium.launch(args=["--no-sandbox"])
    page = browser.new_page(viewport={"width": width, "height": height})
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    return browser, page, errors


def drive(url: str, plan: dict, screenshot: str, chromium: str | None = None) -> dict:
    from playwright.sync_api import sync_playwright

    log = {}
    with sync_playwright() as p:
        browser, page, errors = open_page(p, url, chromium, 1400, 800)
        log["console_errors"] = errors
        # selectors, not wait_for_function: the page's CSP forbids the eval that a JS string would need
        page.wait_for_selector("#status:has-text('automatic')", timeout=30000)
        log["loaded"] = page.inner_text("#status")
        page.select_option("#photo-select", plan["view"])
        page.wait_for_timeout(300)
        page.select_option("#car-select", plan["car"])
        page.wait_for_timeout(500)
        # the point on the model: its reference pixel on the face canvas
        face = page.locator(f"#face-{plan['face']}")
        face.scroll_into_view_if_needed()
        box = face.bounding_box()
        ref = page.evaluate("([c, f, n]) => window.pickerState.doc.cars.find(x => x.number === c).faces[f].points[n]",
                            [plan["car"], plan["face"], plan["point"]])
        fw = page.evaluate("([c, f]) => window.pickerState.doc.cars.find(x => x.number === c).faces[f].width",
                           [plan["car"], plan["face"]])
        s = box["width"] / fw
        page.mouse.click(box["x"] + (ref[0] + 0.5) * s, box["y"] + (ref[1] + 0.5) * s)
        log["point_selected"] = page.evaluate("window.pickerState.point")
        # rough pick at fit zoom
        x, y = _screen(page, plan["first_uv"])
        page.mouse.click(x, y)
        log["rough"] = page.inner_text("#status")
        # zoom in at the true place, careful pick
        x, y = _screen(page, plan["uv"])
        page.mouse.move(x, y)
        for _ in range(6):
            page.mouse.wheel(0, -120)
            page.wait_for_timeout(50)
        log["scale"] = page.evaluate("window.pickerState.scale")
        x, y = _screen(page, plan["uv"])
        page.mouse.click(x, y)
        log["careful"] = page.inner_text("#status")
        page.keyboard.press("Control+z")
        log["undo"] = page.inner_text("#status")
        log["after_undo"] = page.evaluate("window.pickerState.manual.slice(-1)[0]")
        x, y = _screen(page, plan["uv"])
        page.mouse.click(x, y)
        if plan.get("reject_point"):  # review: an automatic point of this car found wrong, rejected (R)
            page.click(f'#points li[data-point="{plan["reject_point"]}"]')
            page.keyboard.press("r")
            log["rejected"] = page.inner_text("#status")
        page.keyboard.press("Control+s")
        page.wait_for_selector("#status:text-matches('^saved')", timeout=10000)
        log["saved"] = page.inner_text("#status")
        page.screenshot(path=screenshot)
        browser.close()
    return log


def _drag(page, a, b):
    x, y = _screen(page, a)
    page.mouse.move(x, y)
    page.mouse.down()
    x, y = _screen(page, b)
    page.mouse.move(x, y, steps=4)
    page.mouse.up()


def look(url: str, plan: dict, screenshot: str, chromium: str | None = None) -> dict:
    """Open the page on a photo and a carriage, wait for the overlay and the live pose, screenshot (``--look``)."""
    from playwright.sync_api import sync_playwright

    log = {}
    with sync_playwright() as p:
        browser, page, errors = open_page(p, url, chromium, plan.get("width", 1400), plan.get("height", 800))
        log["console_errors"] = errors
        page.wait_for_selector("#status:has-text('automatic')", timeout=30000)
        page.select_option("#photo-select", plan["view"])
        page.wait_for_timeout(500)
        page.select_option("#car-select", plan["car"])
        page.wait_for_timeout(1500)  # the overlay and the live pose answer
        if plan.get("zoom"):  # the view centred on (u, v) at that scale (the page redraws on the magnifier's change)
            u, v, scale = plan["zoom"]
            page.evaluate("""([u, v, k]) => { const S = window.pickerState, cv = document.getElementById('photo-canvas');
                S.scale = k; S.ox = cv.width / 2 - (u + 0.5) * k; S.oy = cv.height / 2 - (v + 0.5) * k; }""", [u, v, scale])
            page.evaluate("document.getElementById('magnify').dispatchEvent(new Event('change'))")
        if plan.get("edges"):
            page.click(f'#points li[data-point="{plan["point"]}"]')
            page.keyboard.press("e")
            for a, b in plan["edges"]:
                _drag(page, a, b)
            log["edges"] = page.inner_text("#status")
            log["edge_pick"] = page.evaluate("window.pickerState.manual.slice(-1)[0]")
            page.wait_for_timeout(1000)
        elif plan.get("point"):
            page.click(f'#points li[data-point="{plan["point"]}"]')
        page.wait_for_timeout(300)
        log["overlay"] = page.evaluate("""() => { const o = window.pickerState.overlay; return o && {available: o.available,
            reason: o.reason, cars: o.cars, n_residuals: o.residuals && o.residuals.length, flagged: o.flagged,
            outline: o.outline && Object.fromEntries(Object.entries(o.outline).map(([k, v]) => [k, v.length]))}; }""")
        log["live"] = page.evaluate("""() => { const l = window.pickerState.live; return l && {pose: !!l.pose, reason: l.reason,
            rms_px: l.rms_px, n_picks: l.n_picks, flagged: l.flagged, focal: l.focal,
            n_predicted: l.predicted && Object.keys(l.predicted[window.pickerState.photo.name] || {}).length}; }""")
        log["checks"] = page.inner_text("#checks")
        page.screenshot(path=screenshot)
        browser.close()
    return log


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("url")
    ap.add_argument("plan")
    ap.add_argument("screenshot")
    ap.add_argument("--chromium", default=None)
    ap.add_argument("--look", action="store_true", help="open a photo and a carriage, screenshot the overlay")
    a = ap.parse_args(argv)
    with open(a.plan, encoding="utf-8") as f:
        plan = json.load(f)
    print(json.dumps((look if a.look else drive)(a.url, plan, a.screenshot, a.chromium)))
    return 0


if __name__ == "__main__":
    sys.exit(main())

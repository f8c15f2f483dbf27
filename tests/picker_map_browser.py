"""Drive the picker's control-point mode in a headless Chromium as a person would (Playwright), for
tests/test_picker_map.py and scripts/bench_picker_georef.py.

    python tests/picker_map_browser.py URL PLAN.json SCREENSHOT.png [--chromium /usr/bin/chromium]

PLAN.json: ``{"photo": "pano_01.jpg", "points": [{"name": "cp_a", "uv": [u, v], "en": [E, N]}, ...]}``. For each
point: New point, rename it, zoom the photo in at ``uv`` (mouse wheel) and click it, fit the photo again; zoom the
map in at ``(E, N)`` and click it (the page asks the server for the DEM's height), fit the map again. Then Save,
Run georef, wait for the result, take a screenshot; optionally (``"roof": [E, N]``) a new point clicked on the
map near a building's corner (it snaps to it) and given the roof's height (Roof). Prints a JSON summary: the points as the page holds them, the
georef result the page shows, the status lines and any console error.
"""

from __future__ import annotations

import argparse
import json
import sys

from picker_browser import open_page  # the sibling driver (tests/ is on the path when either runs)


def _photo_screen(page, uv):
    """Page coordinates of photo pixel ``uv`` (inverse of picker.js toImage)."""
    return page.evaluate(
        """([u, v]) => { const S = window.pickerState, r = document.getElementById('photo-canvas').getBoundingClientRect();
             return [r.left + (u + 0.5) * S.scale + S.ox, r.top + (v + 0.5) * S.scale + S.oy]; }""", list(uv))


def _map_screen(page, en):
    """Page coordinates of project-CRS ``(E, N)`` on the map canvas (inverse of map.js mImage and crsOf)."""
    return page.evaluate(
        """([e, n]) => { const M = window.mapState, A = M.doc.crs_from_pixel, r = document.getElementById('map-canvas').getBoundingClientRect();
             const u = (e - A[0][2]) / A[0][0], v = (n - A[1][2]) / A[1][1];
             return [r.left + (u + 0.5) * M.scale + M.ox, r.top + (v + 0.5) * M.scale + M.oy]; }""", list(en))


def _zoom_click(page, where, at, steps, scale_of):
    """Zoom in with the wheel at ``at``, wait until the page has handled every wheel event (its scale stops
    changing), then click ``at``."""
    x, y = where(page, at)
    page.mouse.move(x, y)
    for _ in range(steps):
        page.mouse.wheel(0, -120)
        page.wait_for_timeout(20)
    last = None
    for _ in range(50):
        page.wait_for_timeout(60)
        now = page.evaluate(scale_of)
        if now == last:
            break
        last = now
    x, y = where(page, at)
    page.mouse.click(x, y)


def drive(url: str, plan: dict, screenshot: str, chromium: str | None = None) -> dict:
    from playwright.sync_api import sync_playwright

    log: dict = {"steps": []}
    with sync_playwright() as p:
        browser, page, errors = open_page(p, url, chromium, plan.get("width", 1500), plan.get("height", 850))
        log["console_errors"] = errors
        page.wait_for_selector("#status:has-text('automatic')", timeout=30000)
        page.select_option("#photo-select", plan["photo"])
        page.wait_for_timeout(300)
        page.select_option("#mode-select", "control")
        page.wait_for_selector("#cp-info:has-text('map:')", timeout=60000)
        page.wait_for_timeout(300)
        for q in plan["points"]:
            page.click("#cp-new")
            page.fill("#cp-name", q["name"])
            page.press("#cp-name", "Enter")
            page.dispatch_event("#cp-name", "change")
            _zoom_click(page, _photo_screen, q["uv"], plan.get("photo_zoom_steps", 6), "() => window.pickerState.scale")
            log["steps"].append(page.inner_text("#status"))
            page.click("#zoom-fit")
            _zoom_click(page, _map_screen, q["en"], plan.get("map_zoom_steps", 12), "() => window.mapState.scale")
            page.wait_for_selector(f"#status:has-text('{q['name']} on the map')", timeout=30000)
            log["steps"].append(page.inner_text("#status"))
            page.evaluate("() => window.dispatchEvent(new Event('resize'))")  # fits the photo and the map again
            page.wait_for_timeout(100)
        page.click("#cp-save")
        page.wait_for_selector("#status:text-matches('^saved')", timeout=30000)
        log["saved"] = page.inner_text("#status")
        page.click("#cp-georef")
        page.wait_for_selector("#status:text-matches('^georef [(]|^georef failed')", timeout=300000)
        log["georef_status"] = page.inner_text("#status")
        log["result_text"] = page.inner_text("#cp-result")
        log["points"] = page.evaluate("() => window.mapState.cps.points")
        log["result"] = page.evaluate("() => window.mapState.result")
        page.screenshot(path=screenshot)
        if plan.get("track"):  # picks on the track: the rail chosen, Track pick, points clicked in the photo, Esc, save
            page.click("#zoom-fit")
            page.select_option("#tp-rail", plan["track"]["rail"])
            page.click("#tp-new")
            for uv in plan["track"]["pixels"]:
                page.mouse.click(*_photo_screen(page, uv))
            log["track_picking"] = page.inner_text("#tp-info")
            page.keyboard.press("Escape")
            page.screenshot(path=screenshot.replace(".png", "_track.png"))
            page.click("#cp-save")
            page.wait_for_selector("#status:text-matches('^saved')", timeout=30000)
            log["track_saved"] = page.inner_text("#status")
            log["track_info"] = page.inner_text("#tp-info")
        if plan.get("roof"):  # a building's corner clicked near it on the map (it snaps), then Roof
            page.click("#cp-new")
            _zoom_click(page, _map_screen, plan["roof"], plan.get("map_zoom_steps", 12), "() => window.mapState.scale")
            page.wait_for_selector("#status:has-text('snapped to a corner')", timeout=30000)
            log["roof_snap"] = page.inner_text("#status")
            page.click("#cp-roof")
            log["roof_status"] = page.inner_text("#status")
            log["roof_point"] = page.evaluate("() => window.mapState.cps.points.slice(-1)[0]")
        browser.close()
    return log


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("url")
    ap.add_argument("plan")
    ap.add_argument("screenshot")
    ap.add_argument("--chromium", default=None)
    a = ap.parse_args(argv)
    with open(a.plan, encoding="utf-8") as f:
        plan = json.load(f)
    print(json.dumps(drive(a.url, plan, a.screenshot, a.chromium)))
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/python3
"""The map viewer in a real browser (headless Debian chromium through chromedriver and selenium).

Starts mapd on a scratch map with the viewer on, uploads simulated passages (mapsim fleet), and
checks against the gRPC API (mapctl --json), computed here independently of the page:
  - the page draws every landmark of the map;
  - one landmark's 95% error ellipse, read back from the canvas's pixels along its axes, has the
    semi-axes and orientation of its covariance, in metres (the pixel scale of Web Mercator at
    the landmark's latitude and the map's zoom);
  - clicking the landmark shows its id, passages seen and version;
  - new passages appear without a reload (polling by version);
  - with authentication on, the API answers 401 without a token and 403 to a vehicle asking for
    passages, and the page draws nothing until given a token.
With --perf-url URL it measures instead a viewer already serving a large map (README, "Map
viewer"): the first draw after navigation, and pan and zoom redraws.
Usage: viewer_browser_test.py --build BUILD_DIR [--screenshot PNG]
       viewer_browser_test.py --perf-url http://HOST:PORT/ [--runs N]
"""
import argparse
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request

from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.action_chains import ActionChains
from selenium.webdriver.common.by import By

EARTH_RADIUS_M = 6378137.0  # Web Mercator (EPSG:3857)
CHI2_2DOF_95 = 5.991464547107979
FAILURES = []


def check(condition, message):
    print(("ok   " if condition else "FAIL ") + message, flush=True)
    if not condition:
        FAILURES.append(message)


class Mapd:
    def __init__(self, build, workdir, name, extra=()):
        self.log_path = os.path.join(workdir, name + ".log")
        self.log = open(self.log_path, "w")
        self.proc = subprocess.Popen(
            [os.path.join(build, "server/mapd"), "--db", os.path.join(workdir, name + ".db"), "--create",
             "--listen", "127.0.0.1:0", "--http-listen", "127.0.0.1:0", "--log-level", "info", *extra],
            stdout=self.log, stderr=subprocess.STDOUT)
        deadline = time.time() + 30
        self.grpc_port = self.http_port = None
        while time.time() < deadline and (self.grpc_port is None or self.http_port is None):
            text = open(self.log_path).read()
            if m := re.search(r"event=started .*? port=(\d+)", text):
                self.grpc_port = int(m.group(1))
            if m := re.search(r"event=http_viewer .*? port=(\d+)", text):
                self.http_port = int(m.group(1))
            if self.proc.poll() is not None:
                break
            time.sleep(0.05)
        if self.grpc_port is None or self.http_port is None:
            raise RuntimeError("mapd did not start:\n" + open(self.log_path).read())
        self.server = f"127.0.0.1:{self.grpc_port}"
        self.url = f"http://127.0.0.1:{self.http_port}/"

    def stop(self):
        self.proc.send_signal(signal.SIGTERM)
        self.proc.wait(timeout=30)
        self.log.close()


def run(args, **kwargs):
    return subprocess.run(args, check=True, capture_output=True, text=True, **kwargs).stdout


def api_landmarks(build, server, token_file=None):
    extra = ["--token-file", token_file] if token_file else []
    out = run([os.path.join(build, "client/mapctl"), "region", "--bbox", "-180,-85,180,85", "--json",
               "--server", server, *extra])
    return json.loads(out).get("landmarks", [])


def api_info(build, server):
    return json.loads(run([os.path.join(build, "client/mapctl"), "info", "--json", "--server", server]))


def ellipse95(cov):
    """Semi-axes (m) and the major axis's azimuth (rad, clockwise from North) of a 2x2 E/N covariance."""
    ee, en, nn = cov["ee"], 0.5 * (cov["en"] + cov["ne"]), cov["nn"]
    mean, half = 0.5 * (ee + nn), math.hypot(0.5 * (ee - nn), en)
    azimuth = 0.5 * math.atan2(2 * en, ee - nn)  # major axis angle from East, counterclockwise
    return (math.sqrt(CHI2_2DOF_95 * (mean + half)), math.sqrt(CHI2_2DOF_95 * max(mean - half, 0.0)),
            math.pi / 2 - azimuth)


def browser():
    options = webdriver.ChromeOptions()
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
              "--window-size=1200,800", "--force-device-scale-factor=1"):
        options.add_argument(a)
    options.binary_location = "/usr/bin/chromium"
    return webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=options)


def wait_for(driver, script, timeout_s=20.0):
    deadline = time.time() + timeout_s
    while time.time() < deadline:
        value = driver.execute_script(script)
        if value:
            return value
        time.sleep(0.05)
    return driver.execute_script(script)


def after_frames(driver, action):
    """Runs `action` (JS) in the page and returns the time (ms) until two animation frames later."""
    return driver.execute_async_script(f"""
        const done = arguments[arguments.length - 1];
        const v = window.crowdmapViewer, before = v.draws, t0 = performance.now();
        {action};
        requestAnimationFrame(() => requestAnimationFrame(() =>
            done({{ms: performance.now() - t0, draws: v.draws - before, draw_ms: v.lastDrawMs, drawn: v.drawn}})));
    """)


def edge_px(driver, x, y, dx, dy, max_r):
    """Distance from (x, y) along (dx, dy) to the outermost painted canvas pixel within max_r."""
    return driver.execute_script("""
        const [x, y, dx, dy, maxR] = arguments;
        const c = window.crowdmapViewer.canvas, ctx = c.getContext('2d');
        const data = ctx.getImageData(0, 0, c.width, c.height).data;
        for (let r = maxR; r >= 0; r -= 0.25) {
          const px = Math.round(x + r * dx), py = Math.round(y + r * dy);
          if (px < 0 || py < 0 || px >= c.width || py >= c.height) continue;
          if (data[(py * c.width + px) * 4 + 3] > 64) return r;
        }
        return -1;
    """, x, y, dx, dy, max_r)


def check_drawing(build, mapd, driver, screenshot):
    landmarks = api_landmarks(build, mapd.server)
    info = api_info(build, mapd.server)
    check(len(landmarks) > 10, f"the map has {len(landmarks)} landmarks")
    driver.get(mapd.url)
    check(wait_for(driver, "return window.crowdmapViewer && window.crowdmapViewer.ready") is True, "page ready")
    v = driver.execute_script("const v = window.crowdmapViewer; return {drawn: v.drawn, held: v.landmarks.size,"
                              " version: v.version, first_ms: v.firstDrawMs, error: v.error};")
    check(v["held"] == len(landmarks), f"page holds {v['held']} landmarks, API {len(landmarks)}")
    check(v["drawn"] == len(landmarks), f"page drew {v['drawn']} landmarks, API {len(landmarks)}")
    check(v["version"] == int(info["map_version"]), f"page map version {v['version']}, API {info['map_version']}")

    # The landmark with the most elongated ellipse: its orientation is then well defined.
    lm = max(landmarks, key=lambda l: ellipse95(l["cov_en_m2"])[0] / max(ellipse95(l["cov_en_m2"])[1], 1e-9))
    a_m, b_m, azimuth = ellipse95(lm["cov_en_m2"])
    lat = lm["lat_deg"]
    ground_m_per_px_z0 = 2 * math.pi * EARTH_RADIUS_M * math.cos(math.radians(lat)) / 256
    zoom = int(math.floor(math.log2(60 * ground_m_per_px_z0 / a_m)))  # major semi-axis 60-120 px
    m_per_px = ground_m_per_px_z0 / 2 ** zoom
    driver.execute_script("window.crowdmapViewer.map.setView([arguments[0], arguments[1]], arguments[2]);",
                          lat, lm["lon_deg"], zoom)
    time.sleep(0.3)
    centre = driver.execute_script(
        "const p = window.crowdmapViewer.map.latLngToContainerPoint([arguments[0], arguments[1]]); return [p.x, p.y];",
        lat, lm["lon_deg"])
    line_half_width_px = 1.0  # the page strokes 2 px wide
    # Screen directions (y down) of the major axis (azimuth clockwise from North) and the minor one.
    major = (math.sin(azimuth), -math.cos(azimuth))
    minor = (math.cos(azimuth), math.sin(azimuth))
    for name, direction, expected_m in (("major", major, a_m), ("minor", minor, b_m)):
        for sign in (1, -1):
            r = edge_px(driver, centre[0], centre[1], sign * direction[0], sign * direction[1],
                        2.0 * a_m / m_per_px)
            drawn_m = (r - line_half_width_px) * m_per_px
            ok = abs(drawn_m - expected_m) <= max(0.03 * expected_m, 1.5 * m_per_px)
            check(ok, f"landmark {lm['id']} {name} semi-axis {'+' if sign > 0 else '-'}: drawn {drawn_m:.3f} m, "
                      f"API covariance {expected_m:.3f} m (zoom {zoom}, {m_per_px * 100:.2f} cm/px)")

    # Click its centre: the details show what the API says.
    map_element = driver.find_element(By.ID, "map")
    size = map_element.size
    ActionChains(driver).move_to_element_with_offset(
        map_element, int(round(centre[0] - size["width"] / 2)), int(round(centre[1] - size["height"] / 2))).click().perform()
    details = wait_for(driver, "const t = document.getElementById('details-table'); return t && t.innerText;", 5)
    rows = dict(line.split("\t", 1) for line in (details or "").splitlines() if "\t" in line)
    check(rows.get("id") == lm["id"], f"click shows landmark id {rows.get('id')}, expected {lm['id']}")
    check(rows.get("passages seen") == lm["passages_seen"],
          f"click shows passages seen {rows.get('passages seen')}, API {lm['passages_seen']}")
    check(rows.get("version") == lm["version"], f"click shows version {rows.get('version')}, API {lm['version']}")
    if screenshot:  # the selected landmark and its neighbours, for the README
        driver.set_window_size(1000, 560)
        driver.execute_script("window.crowdmapViewer.map.invalidateSize();"
                              "window.crowdmapViewer.map.setView([arguments[0], arguments[1]], arguments[2]);",
                              lat, lm["lon_deg"], zoom - 3)
        time.sleep(0.5)
        driver.save_screenshot(screenshot)
        driver.set_window_size(1200, 800)
    return lm


def check_live_update(build, mapd, driver, workdir):
    files = os.path.join(workdir, "more")
    run([os.path.join(build, "client/mapsim"), "export-passages", "--passages", "3", "--seed", "7",
         "--out", files])
    before = driver.execute_script("return window.crowdmapViewer.version;")
    run([os.path.join(build, "client/mapctl"), "upload", "--server", mapd.server,
         *sorted(os.path.join(files, f) for f in os.listdir(files))])
    deadline = time.time() + 60
    while time.time() < deadline:
        info = api_info(build, mapd.server)
        if int(info.get("queue_depth", 0)) == 0 and int(info["map_version"]) > before:
            break
        time.sleep(0.2)
    landmarks = api_landmarks(build, mapd.server)
    version = int(api_info(build, mapd.server)["map_version"])
    seen = wait_for(driver, f"const v = window.crowdmapViewer; return v.version === {version} && v.version;", 15)
    check(seen == version, f"page followed the map to version {version} without a reload (was {before})")
    held = driver.execute_script("return window.crowdmapViewer.landmarks.size;")
    check(held == len(landmarks), f"after the update the page holds {held} landmarks, API {len(landmarks)}")
    changed = driver.execute_script(
        "return [...window.crowdmapViewer.landmarks.values()].map(l => [String(l.id), String(l.version)]);")
    check(sorted(changed) == sorted([l["id"], l["version"]] for l in landmarks),
          "every landmark's version on the page equals the API's")


def http_get(url, token=None):
    request = urllib.request.Request(url, headers={"Authorization": "Bearer " + token} if token else {})
    try:
        with urllib.request.urlopen(request, timeout=10) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


def check_auth(build, workdir, driver):
    tokens = {}
    with open(os.path.join(workdir, "auth"), "w") as auth:
        for role, name in (("admin", "ops"), ("vehicle", "sim-0")):
            tokens[role] = f"token-{role}-{os.getpid()}"
            digest = subprocess.run(["sha256sum"], input=tokens[role], capture_output=True, text=True).stdout.split()[0]
            auth.write(f"sha256:{digest} {role} {name}\n")
    token_file = os.path.join(workdir, "admin.token")
    with open(token_file, "w") as f:
        f.write(tokens["admin"])
    mapd = Mapd(build, workdir, "auth", ["--auth", "on", "--auth-file", os.path.join(workdir, "auth")])
    try:
        run([os.path.join(build, "client/mapsim"), "fleet", "--server", mapd.server, "--passages", "3",
             "--vehicles", "1", "--quiet", "--token-file", token_file, "--out", os.path.join(workdir, "fleet-auth")])
        n = len(api_landmarks(build, mapd.server, token_file))
        base = mapd.url + "api/landmarks?bbox=-180,-85,180,85"
        check(http_get(base)[0] == 401, "auth on: /api/landmarks without a token is 401")
        check(http_get(base, "not-a-token")[0] == 401, "auth on: /api/landmarks with an unknown token is 401")
        check(http_get(mapd.url + "api/info")[0] == 401, "auth on: /api/info without a token is 401")
        status, body = http_get(base, tokens["vehicle"])
        check(status == 200 and len(json.loads(body)["features"]) == n, "auth on: a vehicle token reads the landmarks")
        check(http_get(mapd.url + "api/passages?state=applied", tokens["vehicle"])[0] == 403,
              "auth on: a vehicle token may not list passages (403)")
        status, body = http_get(mapd.url + "api/passages?state=applied", tokens["admin"])
        check(status == 200 and len(json.loads(body)["passages"]) == 3, "auth on: an admin lists the 3 passages")
        check(http_get(mapd.url)[0] == 200, "auth on: the page itself (no map data) is served")
        driver.get(mapd.url)
        wait_for(driver, "return window.crowdmapViewer && window.crowdmapViewer.error;", 10)
        check(driver.execute_script("return window.crowdmapViewer.landmarks.size;") == 0,
              "auth on: the page holds no landmark without a token")
        driver.find_element(By.ID, "token").send_keys(tokens["vehicle"])
        driver.find_element(By.ID, "token-save").click()
        ready = wait_for(driver, "return window.crowdmapViewer.ready;", 10)
        drawn = driver.execute_script("return window.crowdmapViewer.drawn;")
        check(ready is True and drawn == n, f"auth on: with a token the page draws {drawn} landmarks, API {n}")
        driver.execute_script("sessionStorage.clear();")
    finally:
        mapd.stop()


def measure(url, runs):
    """First draw and pan / zoom redraws of the viewer at `url`, `runs` page loads."""
    driver = browser()
    driver.set_script_timeout(30)
    try:
        first, held, pans, zooms, draws = [], 0, [], [], []
        for _ in range(runs):
            driver.get(url)
            if wait_for(driver, "return window.crowdmapViewer && window.crowdmapViewer.ready", 60) is not True:
                print("perf: the page never became ready")
                return 1
            v = driver.execute_script("const v = window.crowdmapViewer;"
                                      " return {first: v.firstDrawMs, held: v.landmarks.size, drawn: v.drawn};")
            first.append(v["first"])
            held = v["held"]
            for dx, dy in ((300, 0), (0, 200), (-300, -200)):
                r = after_frames(driver, f"v.map.panBy([{dx}, {dy}], {{animate: false}})")
                pans.append(r["ms"])
                draws.append(r["draw_ms"])
            for dz in (1, -1, 1, -1):
                r = after_frames(driver, f"v.map.setZoom(v.map.getZoom() + ({dz}), {{animate: false}})")
                zooms.append(r["ms"])
                draws.append(r["draw_ms"])
        pct = lambda xs, q: sorted(xs)[min(len(xs) - 1, int(q * (len(xs) - 1) + 0.5))]
        print(f"perf: landmarks={held} runs={runs} first_draw_ms max={max(first):.0f} "
              f"(all: {', '.join(f'{x:.0f}' for x in first)}) pan_ms p50={pct(pans, 0.5):.1f} max={max(pans):.1f} "
              f"zoom_ms p50={pct(zooms, 0.5):.1f} max={max(zooms):.1f} canvas_draw_ms p50={pct(draws, 0.5):.1f} "
              f"max={max(draws):.1f}")
        return 0
    finally:
        driver.quit()


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--build")
    parser.add_argument("--screenshot")
    parser.add_argument("--perf-url")
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    if args.perf_url:
        return measure(args.perf_url, args.runs)
    if not args.build:
        parser.error("--build is required (or --perf-url)")
    build = os.path.abspath(args.build)
    workdir = tempfile.mkdtemp(prefix="viewer-test-")
    driver = None
    mapd = None
    try:
        mapd = Mapd(build, workdir, "map")
        run([os.path.join(build, "client/mapsim"), "fleet", "--server", mapd.server, "--passages", "10",
             "--vehicles", "2", "--quiet", "--out", os.path.join(workdir, "fleet")])
        driver = browser()
        driver.set_script_timeout(30)
        check_drawing(build, mapd, driver, args.screenshot)
        check_live_update(build, mapd, driver, workdir)
        mapd.stop()
        mapd = None
        check_auth(build, workdir, driver)
    finally:
        if driver is not None:
            driver.quit()
        if mapd is not None:
            mapd.stop()
    if FAILURES:
        print(f"{len(FAILURES)} check(s) failed; logs in {workdir}")
        return 1
    shutil.rmtree(workdir, ignore_errors=True)
    print("all checks passed")
    return 0


if __name__ == "__main__":
    sys.exit(main())

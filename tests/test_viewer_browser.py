"""The browser viewer end to end: lungdeform.playback.server + headless Debian Chromium driven by Playwright;
and the viewer's own unit tests (vitest, node) with the real ``/presets.json``.

Runs ``node tests/browser/viewer.test.mjs`` against a server on a free loopback port (and a second
one whose ``/presets.json`` is broken, for the fallback). Screenshots go to
``$LUNGDEFORM_ARTIFACTS/browser`` (default ``tests/artifacts/browser``), printed at the end.
Skips, naming what is missing, without node, viewer/node_modules or /usr/bin/chromium
(``make test`` installs them). The page is the bundle shipped in the package (``make test`` rebuilds
it when ``viewer/src`` is newer), or ``$LUNGDEFORM_VIEWER_BUNDLE``: a folder built with
``npx vite build --outDir DIR`` in ``viewer/``, to test changed sources without touching the package.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from lungdeform.playback.export import glb_bytes
from lungdeform.playback.markers import marker_anchors
from lungdeform.playback.server import ViewerServer, presets_json
from lungdeform.playback.tracefeed import LiveFeed, live_json, trace_json
from tests.breathing.test_trace import breath, write_marker_csv
from tests.browser.support import CHROMIUM, REPO, node_modules_or_skip, run_node, two_lungs


def test_viewer_in_headless_chromium(tmp_path):
    viewer = node_modules_or_skip("playwright-core")
    if not Path(CHROMIUM).exists():
        pytest.skip(f"{CHROMIUM} missing: apt-get install chromium (make test does, as root)")
    artifacts = Path(os.environ.get("LUNGDEFORM_ARTIFACTS", REPO / "tests" / "artifacts")) / "browser"
    model = two_lungs(3)
    anchors = marker_anchors(model, np.array([[90.0, 10.0, -20.0]]), ["tumour"])
    glb = glb_bytes(model, markers=anchors)
    # what the page must show: the presets of lungdeform.breathing.presets as served, and the volume (both
    # lungs, mL) each plays at t = 1 s, tidal · s(1 s), interpolated here from the served samples
    served = json.loads(presets_json())["presets"]
    expect = {"names": [p["name"] for p in served],
              "volume_at_1s": {p["name"]: p["tidal_volume_ml"] * float(np.interp(1.0, p["t_s"], p["s"]))
                               for p in served}}
    # `view --trace b.csv --predict-ms 400`: at playback time 12.05 s (trace time 12.05 s) the newest
    # sample is number 120 (t = 12.0 s, samples every 0.1 s), and the volume shown is its predicted one
    t = np.arange(0.0, 30.0, 0.1)
    feed = trace_json(write_marker_csv(tmp_path / "b.csv", t * 1000, 8 * breath(t)), 400)
    series = json.loads(feed)["trace"]
    expect_trace = {"time": 12.05, "index": 120, "dv": series["predicted_ml"][120] - series["v_ee_ml"],
                    "latency": "predicting 400 ms ahead"}
    # the gate served with it (BeamGate, end-exhale 30 %, 90 % intervals): at a sample time after 15 s
    # where the beam is on and one where it is off, the page must say so, give that sample's interval,
    # and draw the window, the band and the beam bar (pixels of their colours in the gate strip)
    gate = series["gate"]
    on = next(i for i in range(150, t.size) if gate["beam_on"][i])
    off = next(i for i in range(150, t.size) if not gate["beam_on"][i])
    expect_trace["gate"] = {k: {"time": float(t[i]) + 0.05, "index": i, "lo": gate["lo"][i], "hi": gate["hi"][i],
                                "window_high": gate["window_high"][i]} for k, i in (("on", on), ("off", off))}
    # `view --trace - --predict-ms 400`: 100 live samples, then the end of input; the page must show the
    # newest one's predicted volume
    live = LiveFeed(400)
    events = [live.push(ti, xi) for ti, xi in zip(t[:100], 8 * breath(t[:100]))]
    live.end()
    expect_trace["live"] = {"n": 100, "dv": events[-1]["predicted_ml"] - 2400.0,
                            "beam": "BEAM ON" if events[-1]["gate"]["beam_on"] else "BEAM OFF"}
    bundle = os.environ.get("LUNGDEFORM_VIEWER_BUNDLE") or None
    with ViewerServer(glb, bundle=bundle) as server, \
            ViewerServer(glb, presets=b"<html>not json</html>", bundle=bundle) as broken, \
            ViewerServer(glb, trace=feed, bundle=bundle) as traced, \
            ViewerServer(glb, trace=live_json(live), live=live, bundle=bundle) as streamed:
        res = run_node([str(REPO / "tests" / "browser" / "viewer.test.mjs"), server.url, str(artifacts),
                        broken.url, traced.url, streamed.url], cwd=REPO,
                       env={"VIEWER_DIR": str(viewer), "CHROMIUM": CHROMIUM, "EXPECT_PRESETS": json.dumps(expect),
                            "EXPECT_TRACE": json.dumps(expect_trace)},
                       timeout=300)
    print(f"browser screenshots in {artifacts}")
    lines = [ln for ln in res.stdout.splitlines() if ln.startswith("{")]
    assert lines, f"no result from the browser test:\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}"
    report = json.loads(lines[-1])
    assert res.returncode == 0 and report["ok"], report["failures"]
    shots = {p.name for p in artifacts.glob("*.png")}
    assert {"end-exhale.png", "end-inhale.png", "end-inhale-upright.png", "preset-normal-t1.png",
            "preset-copd-t1.png", "presets-server.png", "presets-fallback.png", "trace-predict-400.png"} <= shots
    r = report["results"]
    # every check ran (a check missing from the report would otherwise pass silently)
    assert {"preset list from the server", "presets play the served curves", "preset changes picture",
            "fallback to built-in presets with a note", "fallback shapes play", "no trace panel without a trace",
            "trace plays the predicted volume", "trace HUD shows the latency",
            "live samples play as they arrive", "beam on shown", "beam off shown", "gate strip drawn"} <= set(r)
    print(f"silhouette pixels end-exhale {r['silhouette differs ee/ei']['ee']}, end-inhale "
          f"{r['silhouette differs ee/ei']['ei']}; changed by orientation {r['orientation changes picture']['colour']}, "
          f"by preset normal→copd {r['preset changes picture']['silhouette']} (colour {r['preset changes picture']['colour']}); "
          f"presets {r['preset list from the server']['presets']}; fallback note: {r['fallback to built-in presets with a note']['note']!r}; "
          f"{r['fps readout']['stats']['fps']:.1f} fps; trace HUD: {r['trace HUD shows the latency']['latency']!r}, "
          f"{r['trace HUD shows the latency']['values']!r}; gate: {r['beam on shown']['beam']!r}, "
          f"{r['beam on shown']['gateValues']!r}; gate strip pixels {r['gate strip drawn']['pixels']}")


def test_viewer_unit_tests_in_node(tmp_path):
    # the viewer's pure logic (physics.test.ts, curves.test.ts) under vitest, with the real
    # /presets.json bytes: each served preset must parse and play tidal · s(t) at its sample times
    viewer = node_modules_or_skip("three", "vitest")
    presets = tmp_path / "presets.json"
    presets.write_bytes(presets_json())
    # and the served /trace.json of `view --trace --predict-ms 400` (trace.test.ts plays it)
    t = np.arange(0.0, 30.0, 0.1)
    trace = tmp_path / "trace.json"
    trace.write_bytes(trace_json(write_marker_csv(tmp_path / "b.csv", t * 1000, 8 * breath(t)), 400))
    res = run_node([str(viewer / "node_modules/vitest/vitest.mjs"), "run", "tests/physics.test.ts",
                    "tests/curves.test.ts", "tests/trace.test.ts"], cwd=viewer,
                   env={"LUNGDEFORM_PRESETS": str(presets), "LUNGDEFORM_TRACE": str(trace), "NO_COLOR": "1",
                        "FORCE_COLOR": "0"}, timeout=240)
    out = res.stdout + res.stderr
    assert res.returncode == 0, out[-4000:]
    assert "skipped" not in out.split("Tests")[-1], out[-2000:]  # the presets.json part must run

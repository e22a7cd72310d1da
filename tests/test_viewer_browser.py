"""The browser viewer end to end: lungdeform.server + headless Debian Chromium driven by Playwright.

Runs ``node tests/browser/viewer.test.mjs`` against a server on a free loopback port. Screenshots go
to ``$LUNGDEFORM_ARTIFACTS/browser`` (default ``tests/artifacts/browser``), printed at the end.
Skips, naming what is missing, without node, viewer/node_modules or /usr/bin/chromium
(``make test`` installs them).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from lungdeform.export import glb_bytes, marker_anchors
from lungdeform.server import ViewerServer
from tests.browser.support import CHROMIUM, REPO, node_modules_or_skip, run_node, two_lungs


def test_viewer_in_headless_chromium():
    viewer = node_modules_or_skip("playwright-core")
    if not Path(CHROMIUM).exists():
        pytest.skip(f"{CHROMIUM} missing: apt-get install chromium (make test does, as root)")
    artifacts = Path(os.environ.get("LUNGDEFORM_ARTIFACTS", REPO / "tests" / "artifacts")) / "browser"
    model = two_lungs(3)
    anchors = marker_anchors(model, np.array([[90.0, 10.0, -20.0]]), ["tumour"])
    with ViewerServer(glb_bytes(model, markers=anchors)) as server:
        res = run_node([str(REPO / "tests" / "browser" / "viewer.test.mjs"), server.url, str(artifacts)],
                       cwd=REPO, env={"VIEWER_DIR": str(viewer), "CHROMIUM": CHROMIUM}, timeout=240)
    print(f"browser screenshots in {artifacts}")
    lines = [ln for ln in res.stdout.splitlines() if ln.startswith("{")]
    assert lines, f"no result from the browser test:\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}"
    report = json.loads(lines[-1])
    assert res.returncode == 0 and report["ok"], report["failures"]
    shots = {p.name for p in artifacts.glob("*.png")}
    assert {"end-exhale.png", "end-inhale.png", "end-inhale-upright.png", "preset-quiet-t1.png"} <= shots
    r = report["results"]
    print(f"silhouette pixels end-exhale {r['silhouette differs ee/ei']['ee']}, end-inhale "
          f"{r['silhouette differs ee/ei']['ei']}; changed by orientation {r['orientation changes picture']['colour']}, "
          f"by preset {r['preset changes picture']['silhouette']}; {r['fps readout']['stats']['fps']:.1f} fps")

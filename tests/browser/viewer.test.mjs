// Browser test of the lungdeform viewer: Playwright (playwright-core) drives Debian's Chromium,
// headless, software GL. Run by tests/test_viewer_browser.py, which starts `lungdeform.server` on a
// free loopback port. Usage:
//   node tests/browser/viewer.test.mjs URL ARTIFACT_DIR [FALLBACK_URL] [TRACE_URL] [LIVE_URL]
// Env: VIEWER_DIR (folder whose node_modules holds playwright-core), CHROMIUM (executable),
// EXPECT_PRESETS (JSON from lungdeform.presets: {"names": [...], "volume_at_1s": {name: mL}}).
// FALLBACK_URL: a server whose /presets.json is broken; the viewer must fall back to its built-in
// shapes and say so. TRACE_URL: a server of `view --trace --predict-ms 400`; EXPECT_TRACE (JSON from
// lungdeform.playback.tracefeed): {"time": s, "index": sample, "dv": mL, "latency": text} shown then.
// LIVE_URL: a server of `view --trace -` whose feed holds EXPECT_TRACE.live.n samples (newest: dv mL).
// Exit 0 when every check passes; prints one JSON line of results on stdout.
import { createRequire } from 'node:module';
import { mkdirSync } from 'node:fs';
import path from 'node:path';
import { fileURLToPath } from 'node:url';

const here = path.dirname(fileURLToPath(import.meta.url));
const viewerDir = process.env.VIEWER_DIR ?? path.resolve(here, '../../viewer');
const require = createRequire(path.join(viewerDir, 'package.json'));
const { chromium } = require('playwright-core');

const [url, artifacts, fallbackUrl, traceUrl, liveUrl] = process.argv.slice(2);
if (!url || !artifacts) {
  console.error('usage: node viewer.test.mjs URL ARTIFACT_DIR [FALLBACK_URL]');
  process.exit(2);
}
const expected = JSON.parse(process.env.EXPECT_PRESETS ?? 'null');
const expectTrace = JSON.parse(process.env.EXPECT_TRACE ?? 'null');
mkdirSync(artifacts, { recursive: true });

const failures = [];
const results = {};
function check(name, ok, detail) {
  results[name] = { ok, ...detail };
  if (!ok) failures.push(`${name}: ${JSON.stringify(detail)}`);
}

const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM ?? '/usr/bin/chromium',
  headless: true,
  args: ['--no-sandbox', '--disable-quic', '--no-first-run', '--disable-background-networking',
    '--disable-component-update', '--disable-sync', '--use-angle=swiftshader', '--enable-unsafe-swiftshader',
    '--ignore-gpu-blocklist'],
});
try {
  const page = await browser.newPage({ viewport: { width: 960, height: 640 } });
  const consoleErrors = [];
  page.on('console', (m) => { if (m.type() === 'error') consoleErrors.push(m.text()); });
  page.on('pageerror', (e) => consoleErrors.push(String(e)));
  await page.goto(`${url}?clock=manual`, { waitUntil: 'load' });
  const info = await page.evaluate(() => window.lungdeform.ready);
  check('loads model', info.lungs.length === 2, { info });

  // 0. the preset menu is the server's /presets.json (lungdeform.presets), after the model's own curve
  const menu = await page.locator('#preset option').evaluateAll((os) => os.map((o) => o.value));
  const note = await page.locator('#presets-note');
  const noteText = (await note.textContent()) ?? '';
  check('preset list from the server', info.presetOrigin === 'server' && expected !== null
    && JSON.stringify(info.presets) === JSON.stringify(['model', ...expected.names])
    && JSON.stringify(menu) === JSON.stringify(info.presets)
    && /lungdeform\.presets/.test(noteText) && !(await note.evaluate((e) => e.classList.contains('warning'))),
  { presets: info.presets, menu, note: noteText, expected: expected?.names });
  await page.screenshot({ path: path.join(artifacts, 'presets-server.png') });
  check('no trace panel without a trace', await page.locator('#trace-panel').isHidden(), {});
  // each preset plays the PV model's curve: ΔV(1 s) = tidal · s(1 s) as computed in Python
  const played = await page.evaluate((names) => names.map((n) => {
    window.lungdeform.setPreset(n); window.lungdeform.setTime(1.0); window.lungdeform.renderOnce();
    return window.lungdeform.state().dvMl;
  }), expected?.names ?? []);
  const worst = Math.max(...played.map((v, i) => Math.abs(v - expected.volume_at_1s[expected.names[i]])));
  check('presets play the served curves', played.length > 0 && worst < 1e-6, { played, worst });
  const shot = async (name) => {
    const file = path.join(artifacts, `${name}.png`);
    await page.locator('#view').screenshot({ path: file });
    return file;
  };
  const snap = (key) => page.evaluate((k) => window.lungdeform.snapshot(k), key);
  const diff = (a, b) => page.evaluate(([x, y]) => window.lungdeform.diff(x, y), [a, b]);

  // 1. non-blank frames at end-exhale (phase 0) and end-inhale (phase 0.5 of the model's own curve,
  //    the exporter's plain cosine cycle of 500 mL)
  await page.evaluate(() => { window.lungdeform.setPreset('model'); window.lungdeform.setPhase(0); });
  const ee = await snap('ee');
  await shot('end-exhale');
  await page.evaluate(() => window.lungdeform.setPhase(0.5));
  const ei = await snap('ei');
  await shot('end-inhale');
  const frac = ee.silhouettePixels / (ee.width * ee.height);
  check('non-blank', frac > 0.02 && frac < 0.9, { silhouetteFraction: frac, ee, ei });
  const state = await page.evaluate(() => window.lungdeform.state());
  check('end-inhale volume', Math.abs(state.dvMl - 500) < 1e-6, { dvMl: state.dvMl });

  // the GPU path does no per-vertex work on the CPU: position buffers are never re-uploaded
  const uploads = await page.evaluate(() => window.lungdeform.positionUploads());
  await page.evaluate(() => { for (let i = 0; i < 5; i++) { window.lungdeform.setPhase(i / 5); window.lungdeform.renderOnce(); } });
  check('no per-frame vertex upload', (await page.evaluate(() => window.lungdeform.positionUploads())) === uploads, { uploads });
  await page.evaluate(() => window.lungdeform.setPhase(0.5));

  // 2. the silhouette grows between end-exhale and end-inhale (true model displacement, gain 1)
  const breath = await diff('ee', 'ei');
  check('silhouette differs ee/ei', breath.silhouette > 50 && ei.silhouettePixels > ee.silhouettePixels,
    { ...breath, ee: ee.silhouettePixels, ei: ei.silhouettePixels });

  // 3. orientation changes the picture (same volume, other gravity: other displacement field)
  await snap('supine');
  await page.evaluate(() => window.lungdeform.setOrientation('upright'));
  await snap('upright');
  await shot('end-inhale-upright');
  const orient = await diff('supine', 'upright');
  check('orientation changes picture', orient.colour > 200, orient);
  await page.evaluate(() => window.lungdeform.setOrientation([0.3, 0.2, -0.9]));
  await snap('custom');
  check('custom gravity changes picture', (await diff('upright', 'custom')).colour > 50, {});
  await page.evaluate(() => window.lungdeform.setOrientation('model'));

  // 4. the preset changes the picture at the same time point: normal and copd, both 500 mL breaths
  //    of another shape (at 1 s: 0.44 and 0.75 of the tidal volume)
  await page.evaluate(() => { window.lungdeform.setPreset('normal'); window.lungdeform.setTime(1.0); });
  await snap('normal');
  await shot('preset-normal-t1');
  await page.evaluate(() => { window.lungdeform.setPreset('copd'); window.lungdeform.setTime(1.0); });
  await snap('copd');
  await shot('preset-copd-t1');
  const preset = await diff('normal', 'copd');
  check('preset changes picture', preset.silhouette > 20, preset);

  // 5. overlays and markers render
  await page.evaluate(() => window.lungdeform.setOverlay('force'));
  await snap('force');
  await shot('overlay-force');
  check('force overlay changes colours', (await diff('copd', 'force')).colour > 1000, {});
  await page.evaluate(() => window.lungdeform.setOverlay('none'));
  if (info.markers > 0) {
    await page.evaluate(() => window.lungdeform.setMarkers(true));
    await snap('markers');
    await shot('markers');
    check('markers shown', (await diff('copd', 'markers')).colour > 100, {});
    await page.evaluate(() => window.lungdeform.setMarkers(false));
  }

  // 6. real clock: play for a moment, the readout reports fps and frame time
  await page.evaluate(() => window.lungdeform.play());
  await page.waitForTimeout(1500);
  const stats = await page.evaluate(() => window.lungdeform.stats());
  const readout = await page.locator('#readout').textContent();
  check('fps readout', stats.fps > 0 && /fps \d/.test(readout) && /frame \d/.test(readout), { stats, readout });
  await shot('playing');
  check('no console errors', consoleErrors.length === 0, { consoleErrors });
  await page.close();

  // 7. /presets.json broken: the built-in shapes, and a visible note that says so
  if (fallbackUrl) {
    const fb = await browser.newPage({ viewport: { width: 960, height: 640 } });
    const fbErrors = [];
    fb.on('pageerror', (e) => fbErrors.push(String(e)));
    await fb.goto(`${fallbackUrl}?clock=manual`, { waitUntil: 'load' });
    const fbInfo = await fb.evaluate(() => window.lungdeform.ready);
    const fbNote = fb.locator('#presets-note');
    const text = (await fbNote.textContent()) ?? '';
    await fb.screenshot({ path: path.join(artifacts, 'presets-fallback.png') });
    check('fallback to built-in presets with a note', fbInfo.presetOrigin === 'built-in'
      && fbInfo.presets.includes('cosine') && !fbInfo.presets.includes('normal')
      && (await fbNote.isVisible()) && /built-in/.test(text)
      && (await fbNote.evaluate((e) => e.classList.contains('warning'))) && fbErrors.length === 0,
    { presets: fbInfo.presets, note: text, fbErrors });
    const dv = await fb.evaluate(() => {
      window.lungdeform.setPreset('cosine'); window.lungdeform.setPhase(0.5); window.lungdeform.renderOnce();
      return window.lungdeform.state().dvMl;
    });
    check('fallback shapes play', Math.abs(dv - 500) < 1e-6, { dvMl: dv });
    await fb.close();
  }

  // 8. `view --trace --predict-ms 400`: the trace plays the served predicted volume by sample time,
  //    and the HUD says which latency it compensates
  if (traceUrl && expectTrace) {
    const tp = await browser.newPage({ viewport: { width: 960, height: 640 } });
    const tpErrors = [];
    tp.on('console', (m) => { if (m.type() === 'error') tpErrors.push(m.text()); });
    tp.on('pageerror', (e) => tpErrors.push(String(e)));
    await tp.goto(`${traceUrl}?clock=manual`, { waitUntil: 'load' });
    const tInfo = await tp.evaluate(() => window.lungdeform.ready);
    const st = await tp.evaluate((time) => {
      window.lungdeform.setTime(time); window.lungdeform.renderOnce(); return window.lungdeform.state();
    }, expectTrace.time);
    check('trace plays the predicted volume', tInfo.presets[0] === 'trace' && st.trace?.index === expectTrace.index
      && Math.abs(st.dvMl - expectTrace.dv) < 1e-6 && tpErrors.length === 0,
    { presets: tInfo.presets, state: st.trace, dvMl: st.dvMl, expected: expectTrace, tpErrors });
    const latency = (await tp.locator('#latency').textContent()) ?? '';
    const values = (await tp.locator('#trace-values').textContent()) ?? '';
    check('trace HUD shows the latency', (await tp.locator('#latency').isVisible())
      && latency.startsWith(expectTrace.latency) && /measured \d+ mL {3}predicted \d+ mL/.test(values),
    { latency, values });
    await tp.screenshot({ path: path.join(artifacts, 'trace-predict-400.png') });
    // the gate (EXPECT_TRACE.gate): at a deterministic time the indicator says BEAM ON / BEAM OFF as
    // served for that sample, the HUD gives its interval, and the strip draws window, band and beam bar
    if (expectTrace.gate) {
      for (const which of ['on', 'off']) {
        const e = expectTrace.gate[which];
        const gs = await tp.evaluate((time) => {
          window.lungdeform.setTime(time); window.lungdeform.renderOnce();
          return { ...window.lungdeform.state().trace, pixels: window.lungdeform.gatePixels() };
        }, e.time);
        const want = which === 'on' ? 'BEAM ON' : 'BEAM OFF';
        check(`beam ${which} shown`, gs.index === e.index && gs.beam.startsWith(`${want} (for t + 400 ms)`)
          && gs.beamClass.split(' ').includes(which) && gs.gate.beamOn === (which === 'on')
          && Math.abs(gs.gate.lo - e.lo) < 1e-9 && Math.abs(gs.gate.hi - e.hi) < 1e-9
          && Math.abs(gs.gate.windowHigh - e.window_high) < 1e-9 && /90 % interval \[-?\d/.test(gs.gateValues)
          && /window end-exhale:30/.test(gs.gateValues) && (await tp.locator('#beam').isVisible()),
        { index: gs.index, beam: gs.beam, beamClass: gs.beamClass, gate: gs.gate, gateValues: gs.gateValues, expected: e });
        if (which === 'on') {
          const p = gs.pixels;
          check('gate strip drawn', p.window > 200 && p.band > 100 && p.beamOn > 20 && p.beamOff > 20
            && p.amplitude > 0 && p.predicted > 0, { pixels: p });
        }
        await tp.locator('#trace-panel').screenshot({ path: path.join(artifacts, `trace-gate-beam-${which}.png`) });
      }
    }
    await tp.close();
  }
  // 9. `view --trace -`: samples pushed as Server-Sent Events; the newest one's predicted volume is shown
  if (liveUrl && expectTrace?.live) {
    const lp = await browser.newPage({ viewport: { width: 960, height: 640 } });
    const lpErrors = [];
    lp.on('pageerror', (e) => lpErrors.push(String(e)));
    await lp.goto(`${liveUrl}?clock=manual`, { waitUntil: 'load' });
    await lp.evaluate(() => window.lungdeform.ready);
    await lp.waitForFunction((n) => window.lungdeform.state().trace?.n === n, expectTrace.live.n, { timeout: 20000 });
    const ls = await lp.evaluate(() => { window.lungdeform.renderOnce(); return window.lungdeform.state(); });
    const latency = (await lp.locator('#latency').textContent()) ?? '';
    check('live samples play as they arrive', ls.trace.index === expectTrace.live.n - 1
      && Math.abs(ls.dvMl - expectTrace.live.dv) < 1e-6 && latency.startsWith(expectTrace.latency) && lpErrors.length === 0
      && ls.trace.beam.startsWith(`${expectTrace.live.beam} (for t + 400 ms)`),
    { trace: ls.trace, dvMl: ls.dvMl, expected: expectTrace.live, lpErrors });
    await lp.screenshot({ path: path.join(artifacts, 'live-predict-400.png') });
    await lp.close();
  }
} catch (e) {
  failures.push(`exception: ${e instanceof Error ? e.message : String(e)}`);
} finally {
  await browser.close();
}
console.log(JSON.stringify({ ok: failures.length === 0, failures, results }));
process.exit(failures.length === 0 ? 0 : 1);

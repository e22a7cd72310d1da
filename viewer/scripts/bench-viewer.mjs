// Frame-time benchmark of the viewer in headless Chromium (run by `lungdeform bench viewer`).
// Usage: node scripts/bench-viewer.mjs URL FRAMES [WIDTHxHEIGHT]
// Env: CHROMIUM (executable, default /usr/bin/chromium), CHROMIUM_GL (angle backend: swiftshader
// (default, software) or e.g. vulkan / gl-egl on a GPU machine).
// Prints one JSON line: for each deformation path (gpu: morph targets in the vertex shader; cpu:
// positions blended in JS and re-uploaded), the real-time rAF rate and a synced frame-time series.
import { createRequire } from 'node:module';
import path from 'node:path';
import { fileURLToPath } from 'node:url';

const here = path.dirname(fileURLToPath(import.meta.url));
const require = createRequire(path.join(here, '..', 'package.json'));
const { chromium } = require('playwright-core');

const [url, framesArg, sizeArg] = process.argv.slice(2);
const frames = Number(framesArg ?? 30);
const [width, height] = (sizeArg ?? '960x640').split('x').map(Number);
const gl = process.env.CHROMIUM_GL ?? 'swiftshader';
const args = ['--no-sandbox', '--disable-quic', '--no-first-run', '--disable-background-networking',
  '--disable-component-update', '--disable-sync', '--ignore-gpu-blocklist', `--use-angle=${gl}`,
];
if (gl === 'swiftshader') args.push('--enable-unsafe-swiftshader');
const browser = await chromium.launch({ executablePath: process.env.CHROMIUM ?? '/usr/bin/chromium', headless: true, args });
const out = { url, frames, width, height, angle: gl, runs: [] };
try {
  for (const deform of ['gpu', 'cpu']) {
    const page = await browser.newPage({ viewport: { width, height } });
    page.setDefaultTimeout(600000);
    const t0 = Date.now();
    await page.goto(`${url}?deform=${deform}`, { waitUntil: 'load' });
    const info = await page.evaluate(() => window.lungdeform.ready);
    const loadS = (Date.now() - t0) / 1000;
    await page.waitForTimeout(3000); // real clock, requestAnimationFrame: what a user sees
    const realtime = await page.evaluate(() => window.lungdeform.stats());
    const bench = await page.evaluate((n) => window.lungdeform.bench(n, 3), frames);
    out.runs.push({ deform, loadS, info, realtime, bench });
    await page.close();
  }
} finally {
  await browser.close();
}
console.log(JSON.stringify(out));

// The viewer's preset loading: /presets.json (lungdeform.server) into curves, and the fallback to the
// built-in shapes. With LUNGDEFORM_PRESETS (a presets.json written by tests/test_viewer_browser.py
// from lungdeform.presets) the real document is checked too; that part is skipped without it.
import { readFileSync } from 'node:fs';
import { describe, expect, it } from 'vitest';
import { builtinCurves, loadPresets, parsePresets, presetCurve, volumeAt, type PresetEntry } from '../src/curves';

/** A preset whose s(t) is known in closed form: a raised cosine over one period. */
function cosinePreset(name: string, period: number, n: number, tidal = 500): PresetEntry {
  const t = Array.from({ length: n + 1 }, (_, i) => (i * period) / n);
  return { name, description: `${name} test breath`, period_s: period, tidal_volume_ml: tidal, t_s: t,
           s: t.map((x) => 0.5 * (1 - Math.cos((2 * Math.PI * x) / period))), sources: ['test source'] };
}

const response = (status: number, body: () => Promise<unknown>) =>
  async () => ({ ok: status >= 200 && status < 300, status, json: body });

describe('presetCurve', () => {
  it('plays the served samples at the preset period, tidal volume and rate', () => {
    const p = cosinePreset('a', 4, 200);
    const c = presetCurve(p);
    expect(c.name).toBe('a');
    expect(c.label).toBe('a (15/min, 500 mL)');
    expect(c.source).toMatch(/^lungdeform\.presets \(PV model\): a test breath\. Sources: test source$/);
    expect(c.loopS).toBe(4);
    expect(c.rateBpm).toBeCloseTo(15, 12);
    expect(c.tidalMl).toBe(500);
    expect(c.source).toContain('test source');
    // at the sample times the shape is the served s exactly; in between, linear interpolation
    for (let i = 0; i <= 200; i += 7) expect(c.shape(p.t_s[i] / 4)).toBeCloseTo(p.s[i], 12);
    const mid = c.shape((p.t_s[10] + p.t_s[11]) / 8);
    expect(mid).toBeCloseTo(0.5 * (p.s[10] + p.s[11]), 12);
    // truth: the raised cosine itself, within the interpolation error of 200 samples
    for (const x of [0.1, 0.37, 0.5, 0.81]) expect(Math.abs(c.shape(x) - 0.5 * (1 - Math.cos(2 * Math.PI * x)))).toBeLessThan(2e-4);
    // volumeAt: tidal * s at the preset's own rate; the loop repeats every period
    expect(volumeAt(c, 2, 500, 15)).toBeCloseTo(500, 9);
    expect(volumeAt(c, 1.3, 500, 15)).toBeCloseTo(volumeAt(c, 5.3, 500, 15), 9);
    // a period that the sample rate does not divide (as dyspnoea's 1.875 s): the loop is the period
    const odd = presetCurve(cosinePreset('b', 1.875, 94));
    expect(odd.loopS).toBe(1.875);
    expect(volumeAt(odd, 1.875 / 2, 280, 32)).toBeCloseTo(280, 9);
  });

  it('refuses malformed entries, naming the preset and the problem', () => {
    const ok = cosinePreset('x', 4, 20);
    const cases: [Partial<PresetEntry>, RegExp][] = [
      [{ period_s: 0 }, /preset x: period_s/],
      [{ tidal_volume_ml: -1 }, /preset x: tidal_volume_ml/],
      [{ s: ok.s.slice(1) }, /preset x: t_s and s/],
      [{ t_s: [...ok.t_s.slice(0, -1), 3.9] }, /strictly increasing|one period/],
      [{ s: ok.s.map((v, i) => (i === 3 ? Number.NaN : v)) }, /sample 3/],
      [{ s: ok.s.map((v) => 2 * v) }, /\[0, 1\]/],
      [{ t_s: ok.t_s.map((v) => v * 0.5) }, /one period/],
      [{ name: '' }, /no name/],
    ];
    for (const [change, message] of cases) expect(() => presetCurve({ ...ok, ...change })).toThrow(message);
  });
});

describe('parsePresets and loadPresets', () => {
  const doc = { presets: [cosinePreset('normal', 4, 200), cosinePreset('fast', 2, 100, 300)] };

  it('builds one curve per served preset, in order', () => {
    expect(parsePresets(doc).map((c) => c.name)).toEqual(['normal', 'fast']);
    expect(() => parsePresets({ presets: [] })).toThrow(/empty/);
    expect(() => parsePresets({})).toThrow(/no "presets"/);
    expect(() => parsePresets({ presets: [doc.presets[0], doc.presets[0]] })).toThrow(/repeat/);
  });

  it('uses the server presets when the fetch succeeds', async () => {
    const set = await loadPresets(response(200, async () => doc));
    expect(set.origin).toBe('server');
    expect(set.curves.map((c) => c.name)).toEqual(['normal', 'fast']);
    expect(set.note).toMatch(/2 presets of lungdeform\.presets/);
  });

  it('falls back to the built-in shapes, with a note saying why', async () => {
    const builtin = builtinCurves().map((c) => c.name);
    const failing = [
      [response(404, async () => ({})), /HTTP 404/],
      [response(200, async () => { throw new SyntaxError('Unexpected token o in JSON'); }), /Unexpected token/],
      [response(200, async () => ({ presets: [] })), /empty/],
      [response(200, async () => ({ presets: [{ ...doc.presets[0], s: [0] }] })), /preset normal/],
      [async () => { throw new TypeError('Failed to fetch'); }, /Failed to fetch/],
    ] as const;
    for (const [fetchFn, why] of failing) {
      const set = await loadPresets(fetchFn as never);
      expect(set.origin).toBe('built-in');
      expect(set.curves.map((c) => c.name)).toEqual(builtin);
      expect(set.note).toMatch(/built-in/);
      expect(set.note).toMatch(why);
    }
  });
});

const presetsPath = process.env.LUNGDEFORM_PRESETS;

describe.skipIf(!presetsPath)('the presets.json of lungdeform.presets', () => {
  it('parses, and each curve reproduces its samples at the preset tidal volume', () => {
    const served = JSON.parse(readFileSync(presetsPath!, 'utf-8')) as { presets: PresetEntry[] };
    const curves = parsePresets(served);
    expect(curves.map((c) => c.name)).toEqual(served.presets.map((p) => p.name));
    served.presets.forEach((p, k) => {
      const c = curves[k];
      expect(c.loopS).toBe(p.period_s);
      expect(c.tidalMl).toBe(p.tidal_volume_ml);
      // (the last sample, t = period, is phase 0 of the next loop: s(T) = s(0) to 1e-4, tested in Python)
      for (let i = 0; i < p.t_s.length - 1; i += 5) {
        // volume (mL, both lungs) at the sample time = tidal * s, the PV model's curve
        expect(volumeAt(c, p.t_s[i], c.tidalMl, c.rateBpm)).toBeCloseTo(p.tidal_volume_ml * p.s[i], 6);
      }
      let lo = Infinity, hi = -Infinity;
      for (let i = 0; i <= 2000; i++) { const v = c.shape(i / 2000); lo = Math.min(lo, v); hi = Math.max(hi, v); }
      expect(lo).toBeCloseTo(0, 3); // a 2000-point grid, between the samples
      expect(hi).toBeCloseTo(1, 3);
    });
  });
});

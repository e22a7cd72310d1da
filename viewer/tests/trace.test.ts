// The viewer's trace playback (trace.ts): sample lookup by time, the volume shown, the HUD text. With
// LUNGDEFORM_TRACE (a trace.json written by tests/test_viewer_browser.py from
// lungdeform.playback.tracefeed) the real served document is checked too; skipped without it.
import { readFileSync } from 'node:fs';
import { describe, expect, it } from 'vitest';
import { beamText, gateAt, gateText, latencyText, liveSeries, loadTrace, parseTrace, pushEvent, pushSample, sampleIndex, traceTime, traceVolumeAt, valuesText } from '../src/trace';

/** A served document: n samples dt apart from t0, measured = 2400 + i, predicted = 2400 + 2i. */
function doc(n: number, dt = 0.1, t0 = 0.5, predictMs = 400) {
  const idx = Array.from({ length: n }, (_, i) => i);
  return { schema: 'lungdeform.trace-prediction', trace: {
    source: 'b.csv', unit: 'mm', predict_ms: predictMs, tidal_volume_ml: 500, v_ee_ml: 2400,
    t_s: idx.map((i) => t0 + i * dt), measured_ml: idx.map((i) => 2400 + i), predicted_ml: idx.map((i) => 2400 + 2 * i),
    ahead_s: idx.map(() => predictMs / 1000) } };
}

describe('sampleIndex', () => {
  it('finds the newest sample at or before the time (a live feed shows nothing newer)', () => {
    const t = [0, 0.1, 0.25, 0.4];
    // exactly at a sample: that sample; between samples: the earlier one (causal hold, no interpolation)
    expect([0, 0.1, 0.2499, 0.25, 0.39, 0.4, 9].map((x) => sampleIndex(t, x))).toEqual([0, 1, 1, 2, 2, 3, 3]);
    expect(sampleIndex(t, -1)).toBe(0); // before the first sample: the first
  });
});

describe('trace playback', () => {
  const series = parseTrace(doc(50))!;
  it('plays the predicted volume of the newest sample, above end-exhale', () => {
    // t = 1.03 s of playback = trace time 0.5 + 1.03 = 1.53 s: sample 10 (t 1.5 s), predicted 2400 + 20
    expect(traceVolumeAt(series, 1.03, 500)).toBeCloseTo(20, 12);
    // the tidal control scales the estimator's volumes (500 mL -> 1000 mL doubles them)
    expect(traceVolumeAt(series, 1.03, 1000)).toBeCloseTo(40, 12);
  });
  it('loops over the trace duration from its first sample', () => {
    // duration 4.9 s: playback 4.9 + 0.2 s is trace time 0.5 + 0.2, sample 2
    expect(series.durationS).toBeCloseTo(4.9, 12);
    expect(traceTime(series, 4.9 + 0.2)).toBeCloseTo(0.7, 9);
    expect(traceVolumeAt(series, 5.1 + 1e-9, 500)).toBeCloseTo(4, 12);
  });
  it('says the latency it compensates, or that it compensates none', () => {
    expect(latencyText(series)).toBe('predicting 400 ms ahead (compensates 400 ms of display latency)');
    expect(latencyText(parseTrace(doc(5, 0.1, 0, 0))!)).toMatch(/^no latency compensation/);
    expect(valuesText(series, 1.03)).toBe('t 1.50 s   measured 2410 mL   predicted 2420 mL');
  });
  it('refuses bad documents naming the field, and reads "trace": null as no trace', () => {
    expect(parseTrace({ trace: null })).toBeNull();
    const bad = doc(5);
    bad.trace.predicted_ml[3] = Number.NaN;
    expect(() => parseTrace(bad)).toThrow(/"predicted_ml"\[3\] is not a finite number/);
    const back = doc(5);
    back.trace.t_s[2] = 0;
    expect(() => parseTrace(back)).toThrow(/"t_s" must increase/);
  });
  it('loads through fetch and reports HTTP failures', async () => {
    const ok = async () => ({ ok: true, status: 200, json: async () => doc(3) });
    const got = (await loadTrace(ok))!;
    expect(got.series.n).toBe(3);
    expect(got.liveUrl).toBeNull();
    const missing = async () => ({ ok: false, status: 404, json: async () => ({}) });
    await expect(loadTrace(missing)).rejects.toThrow('trace.json: HTTP 404');
  });
});

describe('live feed', () => {
  const meta = { url: 'live', predict_ms: 300, ahead_s: 0.3, tidal_volume_ml: 500, v_ee_ml: 2400, source: 'stdin' };
  it('shows the newest sample as it arrives, whatever the clock', () => {
    const s = liveSeries(meta, 8);
    // nothing yet: end-exhale (0 mL above it) and a waiting note
    expect(traceVolumeAt(s, 3, 500)).toBe(0);
    expect(valuesText(s, 3)).toBe('waiting for samples…');
    pushEvent(s, JSON.stringify({ t_s: 0.5, measured_ml: 2500, predicted_ml: 2550, ahead_s: 0.3 }));
    pushEvent(s, JSON.stringify({ t_s: 0.6, measured_ml: 2510, predicted_ml: 2600, ahead_s: 0.3 }));
    // the newest sample (t 0.6 s, predicted 2600 mL) is shown at any playback time
    expect(traceVolumeAt(s, 0, 500)).toBe(200);
    expect(traceVolumeAt(s, 99, 500)).toBe(200);
    expect(latencyText(s)).toBe('predicting 300 ms ahead (compensates 300 ms of display latency)');
    expect(() => pushEvent(s, '{"t_s": null}')).toThrow(/live: bad sample/);
  });
  it('keeps the newest samples in the buffers it was given (half dropped when full)', () => {
    const s = liveSeries(meta, 4);
    const buf = s.t;
    for (let i = 0; i < 5; i++) pushSample(s, i, 2400 + i, 2400 + 10 * i);
    // capacity 4: after the 5th sample the oldest two went; samples 2, 3, 4 remain, same buffer
    expect(s.n).toBe(3);
    expect(Array.from(s.t.subarray(0, 3))).toEqual([2, 3, 4]);
    expect(s.t).toBe(buf);
    expect(s.durationS).toBe(2);
    expect(traceVolumeAt(s, 0, 500)).toBe(40);
  });
  it('loads as live when /trace.json says so', async () => {
    const ok = async () => ({ ok: true, status: 200, json: async () => ({ trace: null, live: meta }) });
    const got = (await loadTrace(ok))!;
    expect(got.liveUrl).toBe('live');
    expect(got.series.live && got.series.n === 0).toBe(true);
  });
});

describe('gate', () => {
  /** doc(n) with a gate: beam on at even samples; the interval unknown (null) for the first two. */
  function gated(n: number) {
    const d = doc(n) as ReturnType<typeof doc> & { trace: { gate?: unknown } };
    const idx = Array.from({ length: n }, (_, i) => i);
    d.trace.gate = { window: 'end-exhale:30', rule: 'predicted window probability >= 0.5', coverage: 0.9,
      amplitude: idx.map((i) => i / 10), predicted: idx.map((i) => i / 10 + 1),
      lo: idx.map((i) => (i < 2 ? null : i / 10 + 0.5)), hi: idx.map((i) => (i < 2 ? null : i / 10 + 1.5)),
      window_low: idx.map(() => null), window_high: idx.map(() => 0.9), probability: idx.map(() => null),
      beam_on: idx.map((i) => i % 2 === 0) };
    return d;
  }
  it('reads null as an open window edge or an interval not yet learned', () => {
    const s = parseTrace(gated(10))!;
    // playback 0.25 s = trace time 0.75 s: sample 2 (t 0.7 s), beam on, interval [0.7, 1.7]
    expect(gateAt(s, 0.25)).toEqual({ index: 2, beamOn: true, predicted: 1.2, lo: 0.7, hi: 1.7, windowLow: -Infinity, windowHigh: 0.9 });
    expect(beamText(s, 0.25)).toBe('BEAM ON (for t + 400 ms)');
    expect(beamText(s, 0.35)).toBe('BEAM OFF (for t + 400 ms)');
    expect(gateText(s, 0.25)).toBe('90 % interval [0.70, 1.70] mm   window end-exhale:30 [−∞, 0.90] mm');
    expect(gateText(s, 0.05)).toMatch(/^90 % interval not yet learned/);
    expect(Number.isNaN(gateAt(s, 0.05)!.lo)).toBe(true);
  });
  it('is absent without prediction, and refuses a bad one naming the field', () => {
    expect(gateAt(parseTrace(doc(5))!, 0)).toBeNull();
    expect(beamText(parseTrace(doc(5))!, 0)).toBe('');
    const bad = gated(5);
    (bad.trace.gate as { beam_on: unknown[] }).beam_on[1] = 1;
    expect(() => parseTrace(bad)).toThrow(/"gate.beam_on" must be a list of 5 booleans/);
    const short = gated(5);
    (short.trace.gate as { lo: unknown[] }).lo.pop();
    expect(() => parseTrace(short)).toThrow(/"gate.lo" must be a list of 5 numbers or nulls/);
  });
  it('live: the gate of each event goes into buffers allocated once', () => {
    const meta = { url: 'live', predict_ms: 300, ahead_s: 0.3, tidal_volume_ml: 500, v_ee_ml: 2400, source: 'stdin',
                   gate: { window: 'end-exhale:30', rule: 'r', coverage: 0.9 } };
    const s = liveSeries(meta, 4);
    const buf = s.gate!.lo;
    for (let i = 0; i < 5; i++) {
      pushEvent(s, JSON.stringify({ t_s: i, measured_ml: 2400, predicted_ml: 2400, ahead_s: 0.3, gate: {
        amplitude: i, predicted: i + 1, lo: i === 0 ? null : i, hi: i + 2, window_low: null, window_high: 1, beam_on: i === 4 } }));
    }
    // capacity 4: samples 2, 3, 4 remain in the same buffers; the newest (beam on) is shown
    expect(s.gate!.lo).toBe(buf);
    expect(Array.from(s.gate!.lo.subarray(0, 3))).toEqual([2, 3, 4]);
    expect(gateAt(s, 0)).toEqual({ index: 2, beamOn: true, predicted: 5, lo: 4, hi: 6, windowLow: -Infinity, windowHigh: 1 });
    expect(beamText(s, 0)).toBe('BEAM ON (for t + 300 ms)');
  });
});

const served = process.env.LUNGDEFORM_TRACE;
describe.skipIf(!served)('the served /trace.json', () => {
  it('plays predicted - V_EE at each sample time and says its horizon', () => {
    const raw = JSON.parse(readFileSync(served!, 'utf-8'));
    const s = parseTrace(raw)!;
    const tr = raw.trace;
    // midway to the next sample the shown volume is this sample's predicted volume above end-exhale
    for (let i = 0; i < s.t.length - 1; i += 13) {
      expect(traceVolumeAt(s, 0.5 * (s.t[i] + s.t[i + 1]) - s.t[0], tr.tidal_volume_ml)).toBeCloseTo(tr.predicted_ml[i] - tr.v_ee_ml, 9);
    }
    expect(latencyText(s)).toBe(`predicting ${tr.predict_ms} ms ahead (compensates ${tr.predict_ms} ms of display latency)`);
  });
  it('carries the gate of --predict-ms: per sample the beam decision and the interval as served', () => {
    const raw = JSON.parse(readFileSync(served!, 'utf-8'));
    const s = parseTrace(raw)!;
    const g = raw.trace.gate;
    expect(s.gate).not.toBeNull();
    for (let i = 0; i < s.t.length - 1; i += 7) {
      const at = gateAt(s, 0.5 * (s.t[i] + s.t[i + 1]) - s.t[0])!;
      expect(at.index).toBe(i);
      expect(at.beamOn).toBe(g.beam_on[i]);
      expect(at.lo).toBe(g.lo[i] ?? Number.NaN);
      expect(at.windowHigh).toBe(g.window_high[i] ?? Number.POSITIVE_INFINITY);
    }
  });
});

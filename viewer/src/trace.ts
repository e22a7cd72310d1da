// A recorded breathing trace played in trace time, as served by `lungdeform view MODEL --trace TRACE
// [--predict-ms H]` in /trace.json (lungdeform.playback.tracefeed). Nothing is estimated or predicted
// here: per sample the server sends the causal streaming estimate (measured) and the same with the
// signal predicted ahead_s later (predicted), both from lungdeform.breathing.stream. At trace time t
// the viewer shows the newest sample with t_s <= t (what a live feed would have shown by then).
// Live (`view MODEL --trace -`): /trace.json says "live" and the samples arrive as Server-Sent Events on
// /live, into buffers allocated once (liveSeries, pushSample); the newest sample is shown.

/** The beam gate served with a prediction (lungdeform.breathing.gating.BeamGate), per sample, in the
 * trace's units: the raw amplitude at t_s; the signal predicted for t_s + aheadS with its interval
 * [lo, hi] (NaN before it is learned); the gating window [wLow, wHigh] known at t_s (±Infinity on its
 * open side); the beam decision for t_s + aheadS (1 on, 0 off). */
export interface GateSeries {
  window: string;
  rule: string;
  coverage: number;
  amplitude: Float64Array;
  predicted: Float64Array;
  lo: Float64Array;
  hi: Float64Array;
  wLow: Float64Array;
  wHigh: Float64Array;
  beam: Uint8Array;
}

export interface TraceSeries {
  source: string;
  unit: string;
  /** Prediction horizon (ms; 0: no compensation) and the same in s as served per sample. */
  predictMs: number;
  aheadS: number;
  /** The estimator's tidal volume and end-exhale volume (mL): volume = vEeMl + tidalMl * fraction. */
  tidalMl: number;
  vEeMl: number;
  /** Samples held (the first n entries of the arrays); live: filled as samples arrive. */
  n: number;
  live: boolean;
  /** Per sample: time (s, increasing), measured and predicted lung volume (mL, both lungs). */
  t: Float64Array;
  measured: Float64Array;
  predicted: Float64Array;
  /** Duration (s) of one loop: last sample time minus first. */
  durationS: number;
  /** The beam gate (served with --predict-ms > 0), or null. */
  gate: GateSeries | null;
}

const finite = (x: unknown): x is number => typeof x === 'number' && Number.isFinite(x);

function column(doc: Record<string, unknown>, key: string, n: number): Float64Array {
  const v = doc[key];
  if (!Array.isArray(v) || v.length !== n) throw new Error(`trace.json: "${key}" must be a list of ${n} numbers`);
  const out = new Float64Array(n);
  for (let i = 0; i < n; i++) {
    if (!finite(v[i])) throw new Error(`trace.json: "${key}"[${i}] is not a finite number`);
    out[i] = v[i];
  }
  return out;
}

/** A column that may hold null (JSON for an infinite or unknown bound): null -> ifNull. */
function nullable(doc: Record<string, unknown>, key: string, n: number, ifNull: number): Float64Array {
  const v = doc[key];
  if (!Array.isArray(v) || v.length !== n) throw new Error(`trace.json: "gate.${key}" must be a list of ${n} numbers or nulls`);
  const out = new Float64Array(n);
  for (let i = 0; i < n; i++) {
    if (v[i] === null) out[i] = ifNull;
    else if (finite(v[i])) out[i] = v[i];
    else throw new Error(`trace.json: "gate.${key}"[${i}] is not a number or null`);
  }
  return out;
}

/** The gate of a served trace ("gate": null without prediction); throws on bad data. */
export function parseGate(doc: unknown, n: number): GateSeries | null {
  if (doc === null || doc === undefined) return null;
  const g = doc as Record<string, unknown>;
  const beam = g.beam_on;
  if (!Array.isArray(beam) || beam.length !== n || !beam.every((b) => typeof b === 'boolean')) {
    throw new Error(`trace.json: "gate.beam_on" must be a list of ${n} booleans`);
  }
  if (!finite(g.coverage)) throw new Error('trace.json: "gate.coverage" must be a number');
  return {
    window: String(g.window ?? ''), rule: String(g.rule ?? ''), coverage: g.coverage,
    amplitude: column(g, 'amplitude', n), predicted: nullable(g, 'predicted', n, NaN), lo: nullable(g, 'lo', n, NaN),
    hi: nullable(g, 'hi', n, NaN), wLow: nullable(g, 'window_low', n, -Infinity), wHigh: nullable(g, 'window_high', n, Infinity),
    beam: Uint8Array.from(beam as boolean[], (b) => (b ? 1 : 0)),
  };
}

/** The trace of a parsed /trace.json, or null when it holds none ("trace": null); throws on bad data. */
export function parseTrace(doc: unknown): TraceSeries | null {
  const body = (doc as { trace?: unknown })?.trace;
  if (body === null || body === undefined) return null;
  const tr = body as Record<string, unknown>;
  const n = Array.isArray(tr.t_s) ? tr.t_s.length : 0;
  if (n < 2) throw new Error('trace.json: "t_s" must hold at least 2 samples');
  const t = column(tr, 't_s', n);
  for (let i = 1; i < n; i++) if (!(t[i] > t[i - 1])) throw new Error('trace.json: "t_s" must increase');
  const ahead = column(tr, 'ahead_s', n);
  for (const key of ['predict_ms', 'tidal_volume_ml', 'v_ee_ml']) {
    if (!finite(tr[key])) throw new Error(`trace.json: "${key}" must be a number`);
  }
  return {
    source: typeof tr.source === 'string' ? tr.source : 'trace', unit: typeof tr.unit === 'string' ? tr.unit : '',
    predictMs: tr.predict_ms as number, aheadS: ahead[n - 1], tidalMl: tr.tidal_volume_ml as number,
    vEeMl: tr.v_ee_ml as number, t, measured: column(tr, 'measured_ml', n), predicted: column(tr, 'predicted_ml', n),
    durationS: t[n - 1] - t[0], n, live: false, gate: parseGate(tr.gate, n),
  };
}

/** What /trace.json says of a live feed, or null when there is none. */
export interface LiveMeta { url: string; predict_ms: number; ahead_s: number; tidal_volume_ml: number; v_ee_ml: number; source: string;
  gate?: { window: string; rule: string; coverage: number } | null }

export function parseLive(doc: unknown): LiveMeta | null {
  const live = (doc as { live?: LiveMeta })?.live;
  if (!live) return null;
  for (const key of ['predict_ms', 'ahead_s', 'tidal_volume_ml', 'v_ee_ml'] as const) {
    if (!finite(live[key])) throw new Error(`trace.json: "live.${key}" must be a number`);
  }
  return live;
}

/** An empty live series holding up to capacity samples (buffers allocated here, once). */
export function liveSeries(meta: LiveMeta, capacity = 1 << 15): TraceSeries {
  return { source: meta.source ?? 'stdin', unit: '', predictMs: meta.predict_ms, aheadS: meta.ahead_s,
           tidalMl: meta.tidal_volume_ml, vEeMl: meta.v_ee_ml, t: new Float64Array(capacity),
           measured: new Float64Array(capacity), predicted: new Float64Array(capacity), durationS: 0, n: 0, live: true,
           gate: meta.gate ? { window: meta.gate.window, rule: meta.gate.rule, coverage: meta.gate.coverage,
             amplitude: new Float64Array(capacity), predicted: new Float64Array(capacity), lo: new Float64Array(capacity),
             hi: new Float64Array(capacity), wLow: new Float64Array(capacity), wHigh: new Float64Array(capacity),
             beam: new Uint8Array(capacity) } : null };
}

/** One live sample's gate fields (GATE_KEYS of lungdeform.playback.tracefeed; null: not finite). */
export interface GateEvent { amplitude: number; predicted: number | null; lo: number | null; hi: number | null;
  window_low: number | null; window_high: number | null; beam_on: boolean }

/** Append one live sample; when full, the older half is dropped in place (no allocation). */
export function pushSample(s: TraceSeries, t: number, measuredMl: number, predictedMl: number, gate: GateEvent | null = null): void {
  const cap = s.t.length;
  const g = s.gate;
  if (s.n === cap) {
    const half = cap >> 1;
    for (const a of [s.t, s.measured, s.predicted]) a.copyWithin(0, half, cap);
    if (g) for (const a of [g.amplitude, g.predicted, g.lo, g.hi, g.wLow, g.wHigh, g.beam]) a.copyWithin(0, half, cap);
    s.n = cap - half;
  }
  const i = s.n;
  s.t[i] = t; s.measured[i] = measuredMl; s.predicted[i] = predictedMl;
  if (g) {
    const v = (x: number | null | undefined, ifNull: number) => (finite(x) ? x : ifNull);
    g.amplitude[i] = v(gate?.amplitude, NaN); g.predicted[i] = v(gate?.predicted, NaN);
    g.lo[i] = v(gate?.lo, NaN); g.hi[i] = v(gate?.hi, NaN);
    g.wLow[i] = v(gate?.window_low, -Infinity); g.wHigh[i] = v(gate?.window_high, Infinity);
    g.beam[i] = gate?.beam_on ? 1 : 0;
  }
  s.n++;
  s.durationS = s.t[s.n - 1] - s.t[0];
}

/** Index of the newest of the first n samples with t[i] <= time (binary search; 0 before the first). */
export function sampleIndex(t: ArrayLike<number>, time: number, n = t.length): number {
  if (!(time >= t[0])) return 0;
  let a = 0, b = n - 1;
  if (time >= t[b]) return b;
  while (b - a > 1) { const m = (a + b) >> 1; if (t[m] <= time) a = m; else b = m; }
  return a;
}

/** Trace time (s) at playback time t: the trace loops over its duration from its first sample; live:
 * the newest sample's time (what is shown is what has arrived). */
export function traceTime(series: TraceSeries, t: number): number {
  if (series.live) return series.n > 0 ? series.t[series.n - 1] : 0;
  const d = series.durationS;
  return series.t[0] + (((t % d) + d) % d);
}

/**
 * The volume above end-exhale (mL, both lungs) shown at playback time t: the predicted estimate of
 * the newest sample, scaled from the estimator's tidal volume to the viewer's tidal control.
 */
export function traceVolumeAt(series: TraceSeries, t: number, tidalMl: number): number {
  if (series.n === 0) return 0;
  const i = sampleIndex(series.t, traceTime(series, t), series.n);
  return ((series.predicted[i] - series.vEeMl) * tidalMl) / series.tidalMl;
}

/** The HUD line: the latency the shown volume compensates, or that it compensates none. */
export function latencyText(series: TraceSeries): string {
  const ms = Math.round(series.aheadS * 1000);
  return ms > 0 ? `predicting ${ms} ms ahead (compensates ${ms} ms of display latency)`
    : 'no latency compensation (--predict-ms 0): the measured volume is shown';
}

/** Measured and predicted volume (mL) of the sample shown at playback time t, as one HUD line. */
export function valuesText(series: TraceSeries, t: number): string {
  if (series.n === 0) return 'waiting for samples…';
  const i = sampleIndex(series.t, traceTime(series, t), series.n);
  return `t ${series.t[i].toFixed(2)} s   measured ${series.measured[i].toFixed(0)} mL   predicted ${series.predicted[i].toFixed(0)} mL`;
}

/** The gate at the sample shown at playback time t: the beam decision and its numbers (null: no gate). */
export function gateAt(series: TraceSeries, t: number) {
  const g = series.gate;
  if (!g || series.n === 0) return null;
  const i = sampleIndex(series.t, traceTime(series, t), series.n);
  return { index: i, beamOn: g.beam[i] === 1, predicted: g.predicted[i], lo: g.lo[i], hi: g.hi[i], windowLow: g.wLow[i], windowHigh: g.wHigh[i] };
}

/** The beam indicator's text: BEAM ON or BEAM OFF, for which time, and why (interval vs window). */
export function beamText(series: TraceSeries, t: number): string {
  const s = gateAt(series, t);
  if (!s) return '';
  const ms = Math.round(series.aheadS * 1000);
  return `BEAM ${s.beamOn ? 'ON' : 'OFF'} (for t + ${ms} ms)`;
}

/** The gate's numbers at the sample shown: interval and window, in the trace's units. */
export function gateText(series: TraceSeries, t: number): string {
  const s = gateAt(series, t);
  if (!s || !series.gate) return '';
  const f = (x: number) => (Number.isFinite(x) ? x.toFixed(2) : x > 0 ? '+∞' : x < 0 ? '−∞' : '…');
  const u = series.unit ? ` ${series.unit}` : '';
  const pct = Math.round(series.gate.coverage * 100);
  const band = Number.isFinite(s.lo) ? `[${f(s.lo)}, ${f(s.hi)}]` : 'not yet learned';
  return `${pct} % interval ${band}${u}   window ${series.gate.window} [${f(s.windowLow)}, ${f(s.windowHigh)}]${u}`;
}

type Fetch = (url: string) => Promise<{ ok: boolean; status: number; json(): Promise<unknown> }>;

/** Load /trace.json: the recorded series, an empty live one (live.url: where its events come from), or
 * null when the server plays no trace. Throws, saying why, on failure. */
export async function loadTrace(fetchFn: Fetch, url = 'trace.json'): Promise<{ series: TraceSeries; liveUrl: string | null } | null> {
  const res = await fetchFn(url);
  if (!res.ok) throw new Error(`${url}: HTTP ${res.status}`);
  const doc = await res.json();
  const live = parseLive(doc);
  if (live) return { series: liveSeries(live), liveUrl: live.url };
  const series = parseTrace(doc);
  return series ? { series, liveUrl: null } : null;
}

/** Feed one Server-Sent Event's data (lungdeform.playback.tracefeed.LiveFeed) into a live series. */
export function pushEvent(s: TraceSeries, data: string): void {
  const ev = JSON.parse(data) as { t_s: number; measured_ml: number; predicted_ml: number; gate?: GateEvent };
  if (!finite(ev.t_s) || !finite(ev.measured_ml) || !finite(ev.predicted_ml)) throw new Error(`live: bad sample ${data.slice(0, 80)}`);
  pushSample(s, ev.t_s, ev.measured_ml, ev.predicted_ml, ev.gate ?? null);
}

/**
 * A strip chart of measured and predicted volume over the last windowS seconds of trace time, on a
 * 2-D canvas (drawn from the series in place: no per-frame allocation).
 */
export class StripChart {
  private readonly ctx: CanvasRenderingContext2D | null;
  constructor(private readonly canvas: HTMLCanvasElement, private readonly windowS = 8) {
    this.ctx = canvas.getContext('2d');
  }

  draw(series: TraceSeries, t: number): void {
    const ctx = this.ctx;
    if (!ctx) return;
    const w = this.canvas.width, h = this.canvas.height;
    const now = traceTime(series, t);
    const hi = sampleIndex(series.t, now, series.n), lo = sampleIndex(series.t, now - this.windowS, series.n);
    ctx.fillStyle = '#0f1318';
    ctx.fillRect(0, 0, w, h);
    if (series.n === 0) return;
    const y = (v: number) => h - 3 - ((v - series.vEeMl) / series.tidalMl) * (h - 6);
    const x = (ts: number) => w - ((now - ts) / this.windowS) * w;
    for (const [data, colour] of [[series.measured, '#80cbc4'], [series.predicted, '#ffb74d']] as const) {
      ctx.strokeStyle = colour;
      ctx.lineWidth = 1.5;
      ctx.beginPath();
      for (let i = lo; i <= hi; i++) {
        if (i === lo) ctx.moveTo(x(series.t[i]), y(data[i])); else ctx.lineTo(x(series.t[i]), y(data[i]));
      }
      ctx.stroke();
    }
  }
}

/** The gate strip's colours (opaque, so that a test can count them): window, interval band, beam bar. */
export const GATE_COLOURS = { background: '#0f1318', window: '#1e3a52', windowEdge: '#64b5f6', band: '#7a5a2a',
  amplitude: '#80cbc4', predicted: '#ffb74d', beamOn: '#43a047', beamOff: '#6d2b2b', now: '#9fb3c8' } as const;

/**
 * The gate strip, in the trace's units over the last windowS seconds of trace time and aheadS beyond
 * it: the gating window known at each sample (shaded, its edge a line), the raw amplitude (teal) at t_s,
 * the prediction for t_s + aheadS (orange) with its interval band (clipped to the chart: the vertical
 * scale follows the signal, the prediction and the window edge), and the beam decision for
 * t_s + aheadS as a bar along the bottom (green on, red off); a vertical line marks now. Drawn from
 * the series in place: no per-frame allocation.
 */
export class GateChart {
  private readonly ctx: CanvasRenderingContext2D | null;
  constructor(private readonly canvas: HTMLCanvasElement, private readonly windowS = 8) {
    this.ctx = canvas.getContext('2d');
  }

  draw(series: TraceSeries, t: number): void {
    const ctx = this.ctx, g = series.gate;
    const C = GATE_COLOURS;
    if (!ctx) return;
    const w = this.canvas.width, h = this.canvas.height, bar = 6;
    ctx.fillStyle = C.background;
    ctx.fillRect(0, 0, w, h);
    if (!g || series.n === 0) return;
    const now = traceTime(series, t), ahead = series.aheadS, span = this.windowS + ahead;
    const last = sampleIndex(series.t, now, series.n), first = sampleIndex(series.t, now - this.windowS, series.n);
    let ymin = Infinity, ymax = -Infinity;
    const widen = (v: number) => { if (Number.isFinite(v)) { if (v < ymin) ymin = v; if (v > ymax) ymax = v; } };
    for (let i = first; i <= last; i++) {
      widen(g.amplitude[i]); widen(g.predicted[i]); widen(g.wLow[i]); widen(g.wHigh[i]); // the band is clipped
    }
    if (!(ymax > ymin)) { ymin -= 1; ymax += 1; }
    const pad = 0.05 * (ymax - ymin), top = 2, bottom = h - bar - 2;
    const y = (v: number) => Math.min(bottom, Math.max(top, bottom - ((v - ymin + pad) / (ymax - ymin + 2 * pad)) * (bottom - top)));
    const x = (ts: number) => w - ((now + ahead - ts) / span) * w;
    const next = (i: number) => (i < last ? x(series.t[i + 1]) : x(now + ahead));
    // the window known at each sample, until the next (the newest held to the right edge)
    ctx.fillStyle = C.window;
    for (let i = first; i <= last; i++) {
      const a = y(g.wHigh[i]), b = y(g.wLow[i]);
      ctx.fillRect(x(series.t[i]), a, next(i) - x(series.t[i]) + 0.5, b - a);
    }
    // the interval band at t_s + ahead, over each run of learned samples
    ctx.fillStyle = C.band;
    let run = -1;
    for (let i = first; i <= last + 1; i++) {
      const ok = i <= last && Number.isFinite(g.lo[i]) && Number.isFinite(g.hi[i]);
      if (ok && run < 0) run = i;
      if (!ok && run >= 0) {
        ctx.beginPath();
        for (let k = run; k < i; k++) ctx.lineTo(x(series.t[k] + ahead), y(g.hi[k]));
        for (let k = i - 1; k >= run; k--) ctx.lineTo(x(series.t[k] + ahead), y(g.lo[k]));
        ctx.closePath();
        ctx.fill();
        run = -1;
      }
    }
    ctx.lineWidth = 1;
    const line = (colour: string, data: Float64Array, shift: number) => {
      ctx.strokeStyle = colour;
      ctx.beginPath();
      let pen = false;
      for (let i = first; i <= last; i++) {
        if (!Number.isFinite(data[i])) { pen = false; continue; }
        if (pen) ctx.lineTo(x(series.t[i] + shift), y(data[i])); else ctx.moveTo(x(series.t[i] + shift), y(data[i]));
        pen = true;
      }
      ctx.stroke();
    };
    line(C.windowEdge, g.wHigh, 0);
    line(C.windowEdge, g.wLow, 0);
    line(C.amplitude, g.amplitude, 0);
    line(C.predicted, g.predicted, ahead);
    // the beam decision for t_s + ahead along the bottom
    for (let i = first; i <= last; i++) {
      ctx.fillStyle = g.beam[i] ? C.beamOn : C.beamOff;
      const a = x(series.t[i] + ahead);
      ctx.fillRect(a, h - bar, (i < last ? x(series.t[i + 1] + ahead) : w) - a + 0.5, bar);
    }
    ctx.fillStyle = C.now;
    ctx.fillRect(Math.round(x(now)), 0, 1, h - bar);
  }
}

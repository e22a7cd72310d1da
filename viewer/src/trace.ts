// A recorded breathing trace played in trace time, as served by `lungdeform view MODEL --trace TRACE
// [--predict-ms H]` in /trace.json (lungdeform.playback.tracefeed). Nothing is estimated or predicted
// here: per sample the server sends the causal streaming estimate (measured) and the same with the
// signal predicted ahead_s later (predicted), both from lungdeform.breathing.stream. At trace time t
// the viewer shows the newest sample with t_s <= t (what a live feed would have shown by then).
// Live (`view MODEL --trace -`): /trace.json says "live" and the samples arrive as Server-Sent Events on
// /live, into buffers allocated once (liveSeries, pushSample); the newest sample is shown.

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
    durationS: t[n - 1] - t[0], n, live: false,
  };
}

/** What /trace.json says of a live feed, or null when there is none. */
export interface LiveMeta { url: string; predict_ms: number; ahead_s: number; tidal_volume_ml: number; v_ee_ml: number; source: string }

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
           measured: new Float64Array(capacity), predicted: new Float64Array(capacity), durationS: 0, n: 0, live: true };
}

/** Append one live sample; when full, the older half is dropped in place (no allocation). */
export function pushSample(s: TraceSeries, t: number, measuredMl: number, predictedMl: number): void {
  const cap = s.t.length;
  if (s.n === cap) {
    const half = cap >> 1;
    for (const a of [s.t, s.measured, s.predicted]) a.copyWithin(0, half, cap);
    s.n = cap - half;
  }
  s.t[s.n] = t; s.measured[s.n] = measuredMl; s.predicted[s.n] = predictedMl;
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
  const ev = JSON.parse(data) as { t_s: number; measured_ml: number; predicted_ml: number };
  if (!finite(ev.t_s) || !finite(ev.measured_ml) || !finite(ev.predicted_ml)) throw new Error(`live: bad sample ${data.slice(0, 80)}`);
  pushSample(s, ev.t_s, ev.measured_ml, ev.predicted_ml);
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

// Breathing curves for the viewer: the presets of the PV breathing model served as /presets.json
// (lungdeform.presets simulated by lungdeform.breathing; the single source of the preset shapes), the
// curve stored in the model's glb, and named cycle shapes built in here, used only when
// /presets.json cannot be loaded. A curve gives the volume of both lungs above end-exhale (mL) at
// time t; tidal volume and rate are controls applied on top of its shape.

export interface Curve {
  name: string;
  label: string;
  /** Native tidal volume (mL, peak to peak) and rate (breaths/min). */
  tidalMl: number;
  rateBpm: number;
  /** Duration (s) of one loop of the shape at its native rate. */
  loopS: number;
  /** Normalised shape over one loop: phase in [0, 1) -> [0, 1] (0 = end-exhale, 1 = end-inhale). */
  shape(phase: number): number;
  source: string;
}

const TWO_PI = 2 * Math.PI;

/** Half-cosine rise over the inspiratory fraction rho, then exponential (passive) expiration. */
function riseThenDecay(rho: number, tau: number) {
  const tail = Math.exp(-1 / tau);
  return (phase: number) => {
    if (phase < rho) return 0.5 * (1 - Math.cos((Math.PI * phase) / rho));
    const w = (phase - rho) / (1 - rho);
    return (Math.exp(-w / tau) - tail) / (1 - tail);
  };
}

/** Rise and fall as half cosines with inspiratory fraction rho (rho = 0.5: plain cosine). */
function halfCosines(rho: number) {
  return (phase: number) =>
    phase < rho
      ? 0.5 * (1 - Math.cos((Math.PI * phase) / rho))
      : 0.5 * (1 + Math.cos((Math.PI * (phase - rho)) / (1 - rho)));
}

function periodic(name: string, label: string, tidalMl: number, rateBpm: number,
                  shape: (p: number) => number, source: string): Curve {
  return { name, label, tidalMl, rateBpm, loopS: 60 / rateBpm, shape, source };
}

/** Built-in named cycle shapes: the fallback when /presets.json cannot be loaded. */
export function builtinCurves(): Curve[] {
  return [
    periodic('cosine', 'Plain cycle (cosine, 500 mL, 4 s)', 500, 15,
      (p) => 0.5 * (1 - Math.cos(TWO_PI * p)), 'built-in: the export default'),
    periodic('paper', 'Paper (500 mL, 5 s inhalation)', 500, 6, halfCosines(0.5),
      'built-in: Santhanam et al. 2008 Sec. V, symmetric exhalation assumed'),
    periodic('quiet', 'Quiet (I:E 1:2, passive exhalation)', 500, 12, riseThenDecay(1 / 3, 0.25),
      'built-in: half-cosine inspiration, exponential expiration'),
    periodic('deep', 'Deep breathing (1500 mL)', 1500, 6, riseThenDecay(0.4, 0.3), 'built-in'),
    periodic('exercise', 'Exercise (1200 mL, 30/min)', 1200, 30, halfCosines(0.5), 'built-in'),
  ];
}

/** Count breaths in a sampled curve: upward crossings of its mid level (at least 1). */
export function countCycles(v: ArrayLike<number>): number {
  let lo = Infinity, hi = -Infinity;
  for (let i = 0; i < v.length; i++) { lo = Math.min(lo, v[i]); hi = Math.max(hi, v[i]); }
  const mid = 0.5 * (lo + hi);
  let n = 0;
  for (let i = 1; i < v.length; i++) if (v[i - 1] < mid && v[i] >= mid) n++;
  return Math.max(n, 1);
}

/** A curve from samples t_s (increasing) and volume_ml; loops over its whole duration. */
export function sampledCurve(name: string, label: string, t: number[], v: number[], source: string): Curve {
  if (t.length < 2 || t.length !== v.length) throw new Error(`curve ${name}: need >= 2 matching samples`);
  const t0 = t[0], dur = t[t.length - 1] - t0;
  if (!(dur > 0)) throw new Error(`curve ${name}: zero duration`);
  let lo = Infinity, hi = -Infinity;
  for (const x of v) { lo = Math.min(lo, x); hi = Math.max(hi, x); }
  const span = hi - lo || 1;
  const cycles = countCycles(v);
  const shape = (phase: number) => {
    const tt = t0 + phase * dur;
    let a = 0, b = t.length - 1;
    while (b - a > 1) { const m = (a + b) >> 1; if (t[m] <= tt) a = m; else b = m; }
    const f = (tt - t[a]) / (t[b] - t[a]);
    return ((1 - f) * v[a] + f * v[b] - lo) / span;
  };
  return { name, label, tidalMl: hi - lo, rateBpm: (60 * cycles) / dur, loopS: dur, shape, source };
}

/** Volume (mL, both lungs, above end-exhale) at time t for a curve played at tidal and rate. */
export function volumeAt(curve: Curve, t: number, tidalMl: number, rateBpm: number): number {
  const loop = curve.loopS * (curve.rateBpm / rateBpm);
  const phase = ((t / loop) % 1 + 1) % 1;
  return tidalMl * curve.shape(phase);
}

/** Duration (s) of one loop at the given rate. */
export function loopDuration(curve: Curve, rateBpm: number): number {
  return curve.loopS * (curve.rateBpm / rateBpm);
}

// ------------------------------------------------------------------ /presets.json (lungdeform.server)

/** One preset of /presets.json (lungdeform.server.presets_payload). */
export interface PresetEntry {
  name: string;
  description: string;
  /** Period (s) and the preset's tidal volume (mL, both lungs). */
  period_s: number;
  tidal_volume_ml: number;
  /** One cycle: t_s over [0, period_s] (0 = onset of inspiration), s = (V - V_EE)/dV in [0, 1]. */
  t_s: number[];
  s: number[];
  sources: string[];
}

const finite = (x: unknown): x is number => typeof x === 'number' && Number.isFinite(x);

/** A curve from one /presets.json entry; throws, naming the preset and the field, on bad data. */
export function presetCurve(p: PresetEntry): Curve {
  const name = typeof p?.name === 'string' && p.name ? p.name : '?';
  const bad = (what: string) => new Error(`preset ${name}: ${what}`);
  if (name === '?') throw bad('no name');
  if (!finite(p.period_s) || p.period_s <= 0) throw bad('period_s must be > 0');
  if (!finite(p.tidal_volume_ml) || p.tidal_volume_ml <= 0) throw bad('tidal_volume_ml must be > 0');
  const t = p.t_s, s = p.s;
  if (!Array.isArray(t) || !Array.isArray(s) || t.length < 2 || t.length !== s.length) {
    throw bad('t_s and s must be arrays of one length (>= 2)');
  }
  for (let i = 0; i < t.length; i++) {
    if (!finite(t[i]) || !finite(s[i])) throw bad(`sample ${i} is not a finite number`);
    if (i > 0 && !(t[i] > t[i - 1])) throw bad('t_s must be strictly increasing');
    if (s[i] < -1e-9 || s[i] > 1 + 1e-9) throw bad('s must lie in [0, 1]');
  }
  const period = p.period_s;
  if (Math.abs(t[0]) > 1e-9 * period || Math.abs(t[t.length - 1] - period) > 1e-6 * period) {
    throw bad('t_s must cover one period, 0 … period_s');
  }
  const shape = (phase: number) => {
    const tt = phase * period;
    let a = 0, b = t.length - 1;
    while (b - a > 1) { const m = (a + b) >> 1; if (t[m] <= tt) a = m; else b = m; }
    const f = Math.min(Math.max((tt - t[a]) / (t[b] - t[a]), 0), 1);
    return (1 - f) * s[a] + f * s[b];
  };
  const description = typeof p.description === 'string' && p.description ? `: ${p.description}` : '';
  const sources = Array.isArray(p.sources) ? p.sources.filter((x) => typeof x === 'string') : [];
  const rate = 60 / period;
  const short = (x: number) => String(Number(x.toPrecision(4)));
  return {
    name, label: `${name} (${short(rate)}/min, ${short(p.tidal_volume_ml)} mL)`, tidalMl: p.tidal_volume_ml,
    rateBpm: rate, loopS: period, shape,
    source: `lungdeform.presets (PV model)${description}${sources.length ? '. Sources: ' + sources.join('; ') : ''}`,
  };
}

/** The curves of a parsed /presets.json document; throws when it holds none or a bad entry. */
export function parsePresets(doc: unknown): Curve[] {
  const list = (doc as { presets?: unknown })?.presets;
  if (!Array.isArray(list)) throw new Error('no "presets" list');
  if (list.length === 0) throw new Error('the "presets" list is empty');
  const curves = list.map((p) => presetCurve(p as PresetEntry));
  const names = new Set(curves.map((c) => c.name));
  if (names.size !== curves.length) throw new Error('preset names repeat');
  return curves;
}

export interface PresetSet {
  curves: Curve[];
  /** 'server': from /presets.json; 'built-in': the fallback shapes (see note). */
  origin: 'server' | 'built-in';
  note: string;
}

type Fetch = (url: string) => Promise<{ ok: boolean; status: number; json(): Promise<unknown> }>;

/** Load /presets.json; on any failure fall back to the built-in shapes, saying why in `note`. */
export async function loadPresets(fetchFn: Fetch, url = 'presets.json'): Promise<PresetSet> {
  let reason: string;
  try {
    const res = await fetchFn(url);
    if (!res.ok) {
      reason = `HTTP ${res.status}`;
    } else {
      const curves = parsePresets(await res.json());
      return { curves, origin: 'server', note: `${curves.length} presets of lungdeform.presets (PV breathing model)` };
    }
  } catch (e) {
    reason = e instanceof Error ? e.message : String(e);
  }
  return {
    curves: builtinCurves(), origin: 'built-in',
    note: `Breathing presets unavailable (${url}: ${reason}); showing the viewer's built-in cycle shapes.`,
  };
}
